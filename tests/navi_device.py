"""`navi` on a CUDA host whose Python has the hot-path packages on PYTHONPATH but no installed entry point
(tests/gpu_env.sh defines `navi` as `python tests/navi_device.py`): the same command app as `navi`."""

from __future__ import annotations

from navi.cli import main

if __name__ == "__main__":
    main()
