"""``hapticd view``: a web page of a running hapticd, served by a separate process.

The view is a client of the daemon's control socket, like ``hapticd watch``: one
connection subscribed to telemetry, one that polls the status (and, with
``--control``, sends ``set`` commands). It serves the page (package data: HTML, JS
and CSS, drawn on a canvas; nothing from the network) over HTTP and streams
telemetry to it as Server-Sent Events (docs/view.md).

Standard library only, like the control client: the servo process never loads it.
"""

from hapticd.view.server import ViewServer, is_loopback

__all__ = ["ViewServer", "is_loopback"]
