"""The dashboard: web pages for the service at ``/ui`` (see ``server/ui/router.py``)."""

from server.ui.router import router

__all__ = ["router"]
