"""Navi service mesh: one Zenoh session per process, typed pub/sub over the navi_contracts codec,
liveliness tokens, Prometheus metrics, and the `navi serve` / `navi stack` commands.

Only service entry points import this package; the training core never does.
"""
