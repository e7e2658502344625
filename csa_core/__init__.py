"""CSA core: continual semantic adaptation through neural rendering.

Data flows one way: ``data -> nerf / seg -> adapt -> eval``. Nothing in this package
imports the web server or the client.
"""

__version__ = "0.1.0"
