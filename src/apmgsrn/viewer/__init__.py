"""The interactive viewer (``apmgsrn view``): a web page served by the machine that holds the models.

Layers, each usable on its own: ``catalog`` (what under PATH may be listed and opened; what is opened is
an :class:`apmgsrn.sources.RenderSource`, the same as ``apmgsrn render`` draws), ``orbit`` (the camera as
the user steers it), ``settings`` (settings, colour maps and the transfer function they make), ``worker``
(the progressive render thread, on :mod:`apmgsrn.rendering.progressive`), ``session`` (one viewer's state,
no web code), ``overlay`` (feature-grid and brick boxes drawn with the frame's camera), ``files`` (what
the server saves) and the trame page: ``page_state``, ``layout``, ``webpage`` and ``app``. Importing
this package imports none of trame: ``app`` and ``layout`` do, on use.
"""
