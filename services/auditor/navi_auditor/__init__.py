"""navi_auditor: watching and steering training from outside, never inside the loop.

  server.py, dashboard.py, state.py, hub.py, feed.py   the passive web dashboard (`navi serve auditor`):
                   Zenoh telemetry -> WebSocket -> the browser code in static/
  recorder.py, replay.py   Zenoh streams <-> Zarr v3 session stores (`navi record`, `navi replay`)
  explorer.py, demos.py, bc.py   keyboard flights in the browser saved as demonstrations, and
                   behavioural cloning from them (`navi explore`, `navi bc`)
docs/AUDITOR.md describes them.
"""
