"""The interactive viewer (``apmgsrn view``): a web page served by the machine that holds the models.

Layers, each usable on its own: ``catalog`` (what under PATH may be listed and opened), ``sources``
(a model or volume opened for viewing), ``overlay`` (feature-grid and brick boxes drawn with the
frame's camera), ``session`` (camera control, settings and the progressive render worker; no web code)
and ``app`` (the trame page). Importing this package imports none of trame: ``app`` does, on use.
"""
