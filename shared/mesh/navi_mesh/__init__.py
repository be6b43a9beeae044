"""Navi service mesh: one Zenoh session per process, typed pub/sub over the navi_contracts codec,
liveliness tokens and Prometheus metrics. It imports nothing of Navi but navi_contracts; the commands
that start services (`navi serve`, `navi stack`) live in the `navi` package on top.

Only service entry points import this package; the training core never does.
"""
