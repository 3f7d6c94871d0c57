"""A model in one self-contained web page (``apmgsrn export --format html``): WebGL2 ray marching in the
browser, with no server, no network and no code from elsewhere."""

from apmgsrn.web.page import export_html

__all__ = ["export_html"]
