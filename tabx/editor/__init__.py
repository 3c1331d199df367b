"""The scenario editor: a local web page served by a small stdlib HTTP server.

`tabx editor [NAME] [--port P]` starts the server on 127.0.0.1 and prints its address. The page
(`static/`: plain HTML, JavaScript and CSS, no build step, nothing fetched from the network)
talks to a JSON API (`server.py`) that loads, validates and saves scenarios with
`tabx.scenarios` and runs previews in the simulator (`preview.py`). See docs/editor.md.
"""

from tabx.editor.server import EditorApp, EditorServer, make_server

__all__ = ["EditorApp", "EditorServer", "make_server"]
