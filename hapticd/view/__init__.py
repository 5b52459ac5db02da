"""``hapticd view``: a web page of a running hapticd, served by a separate process.

The view is a client of the daemon's control socket, like ``hapticd watch``: one
connection subscribed to telemetry, one that polls the status (and, with
``--control``, sends ``set`` commands; the subject's answers as ``respond``). It
serves the page (package data: HTML, JS and CSS, drawn on a canvas; nothing from
the network) and talks to each page over one WebSocket (docs/view.md).

A client of the daemon like the control client, with one library besides the
standard one (``websockets``); the servo process never loads it.
"""

from hapticd.view.server import ViewServer, is_loopback

__all__ = ["ViewServer", "is_loopback"]
