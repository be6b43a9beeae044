"""A rank of a data-parallel `navi bench learn` run: torchrun starts this module with the run's job file
(`python -m torch.distributed.run --nproc-per-node N -m navi_bench.learn_rank JOB`;
navi_bench.learn.run_ranks does it for `navi bench learn --nproc N`)."""

from __future__ import annotations

import sys
from pathlib import Path

from navi_bench.learn import rank_main

if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m navi_bench.learn_rank JOB_FILE (started by torchrun)")
    rank_main(Path(sys.argv[1]))
