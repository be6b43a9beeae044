"""Synchronous data-parallel PPO (DD-PPO) over torch.distributed: one process per device.

Launched by torchrun (`torchrun --standalone --nproc-per-node N -m navi train ...`, or `navi train
--nproc N`, which runs exactly that). Each rank owns its actors, flying every scene of the corpus
(TrainConfig.rank_scenes "all") or its share of them ("share": navi_env.corpus.folder.rank_share, dealt
out by trace cost), its env, rollout storage and engine copy on its own device (cuda:LOCAL_RANK, or the
CPU). What crosses ranks, and when:
- start: the run id and folder, then every parameter and buffer of rank 0 (broadcast; after a resume
  too), so all replicas start identical;
- every env step: the RND error's sum, sum of squares and count (3 numbers), all-reduced without
  waiting: launched at step t, waited for at step t + 1, whose normaliser update folds them in
  (Sync.launch_lagged and lagged_previous, called by ppo.compile.PooledForward between two steps'
  graphs, so a rank's rollout step compiles to one graph as a single process's does). The novelty
  normaliser is then the running estimate one process would keep over all actors, one step late, and
  the same on every rank: every rank folds the same pooled sums in at the same step. A run's first step
  waits for its own sums (Sync.sum_kept: the estimate starts from the first batch); the second folds
  them in once more, which leaves the estimate where it is (within rounding). Sums kept per rank and
  pooled once per rollout would instead let the ranks' normalisers drift apart within a rollout, or
  turn the normaliser's per-step moving average into a per-rollout one; one step late keeps its rule
  and identical replicas, and no step waits for the slowest rank's collective of the same step;
- every PPO epoch: each of its minibatches' advantage sums, sums of squares and counts (global
  normalisation: Sync.advantage_moments, one all-reduce for the epoch);
- every minibatch: every gradient, in buckets as DistributedDataParallel packs them: the parameters in
  reverse registration order (about the order backward produces their gradients), a bucket closing at
  NAVI_DIST_BUCKET_MB MiB (default 25). A hook on every parameter (register_post_accumulate_grad_hook)
  counts its gradient in during backward, and a bucket is all-reduced without waiting as soon as all
  its gradients are in and every bucket before it is launched (the same order on every rank). The last
  bucket also carries the non-finite-loss flag (a sum: the skip decision is the same on every rank).
  Before the norm clip every bucket is waited for in order and unpacked (÷ world size) into the
  gradients, so a bucket's unpack overlaps the later buckets' transfers. The eager backward launches a bucket while backward still
  computes the gradients of the next ones. The compiled objective (ppo.compile) runs its backward as one
  graph whose gradients reach the parameters together at its end: its buckets are then launched back to
  back and overlap one another's packing and unpacking only. A parameter backward does not reach sends
  zeros and keeps no gradient. Each element is summed as one flat all-reduce of all gradients sums it:
  on 2 ranks the averaged gradients are bit for bit the same (tested on gloo);
- every update: the stop flags (max: a signal on any rank, a time limit, a monitor) and the mean
  extrinsic reward;
- every log row and checkpoint: the episode statistics (sums).
With world size 1 there is no process group and none of these calls are made: the training loop calls
Solo, Sync's single-process twin, whose every call leaves its values as they are (no hooks, the plain
backward).

With training's StageTimers every wait for a collective is timed as the stage "sync" (a synchronous
collective as a whole, an asynchronous one at its wait), and the stage it lies within leaves that time
out (ppo.timing).

Collectives fail after NAVI_DIST_TIMEOUT_S seconds (default 120): gloo raises, and the error becomes a
DistError naming the timeout; NCCL's watchdog tears the process down (TORCH_NCCL_ASYNC_ERROR_HANDLING=1,
set here unless already set). NAVI_DIST_DEBUG_DIR makes every rank write a hash of its replica there at
the end of a run (the only file a rank other than 0 writes; for tests of replica consistency).
"""

from __future__ import annotations

import functools
import gc
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar, cast

import torch
import torch.distributed as tdist
from torch import nn

from navi_learner.engine.moments import moments_of

TIMEOUT_ENV = "NAVI_DIST_TIMEOUT_S"
"""Seconds a collective may wait for the other ranks before the run fails."""
DEBUG_DIR_ENV = "NAVI_DIST_DEBUG_DIR"
"""Folder where every rank writes rank<r>.json (replica hashes) at the end of a run."""
DEFAULT_TIMEOUT_S = 120.0
BUCKET_ENV = "NAVI_DIST_BUCKET_MB"
"""MiB of gradients per all-reduce bucket (a bucket closes once it holds this much or more)."""
DEFAULT_BUCKET_MB = 25.0

T = TypeVar("T")


class DistError(RuntimeError):
    """A collective failed: a peer rank died, or did not answer within the timeout."""


@dataclass(frozen=True)
class Dist:
    """This process's place in a data-parallel run; the default is a plain single-process run."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    timeout_s: float = DEFAULT_TIMEOUT_S

    @property
    def active(self) -> bool:
        """More than one rank: there is a process group."""
        return self.world > 1

    @property
    def main(self) -> bool:
        """Rank 0, the only rank that writes files (checkpoints, metrics, reports, registry)."""
        return self.rank == 0


def launched() -> bool:
    """This process was started by torchrun (or another launcher that sets WORLD_SIZE)."""
    return "WORLD_SIZE" in os.environ


def timeout_from_env() -> float:
    """NAVI_DIST_TIMEOUT_S as seconds (default 120)."""
    raw = os.environ.get(TIMEOUT_ENV, "").strip()
    try:
        value = float(raw) if raw else DEFAULT_TIMEOUT_S
    except ValueError as err:
        raise ValueError(f"{TIMEOUT_ENV}={raw!r} is not a number of seconds") from err
    if value <= 0:
        raise ValueError(f"{TIMEOUT_ENV} must be positive, got {value}")
    return value


def bucket_mb_from_env() -> float:
    """NAVI_DIST_BUCKET_MB as MiB (default 25)."""
    raw = os.environ.get(BUCKET_ENV, "").strip()
    try:
        value = float(raw) if raw else DEFAULT_BUCKET_MB
    except ValueError as err:
        raise ValueError(f"{BUCKET_ENV}={raw!r} is not a number of MiB") from err
    if value <= 0:
        raise ValueError(f"{BUCKET_ENV} must be positive, got {value}")
    return value


def bucket_plan(sizes: list[int], cap_bytes: int) -> list[list[int]]:
    """The gradient buckets of float32 parameters with `sizes` elements: parameter indices per bucket,
    in reverse registration order, a bucket closing once it holds `cap_bytes` or more. Every index is in
    exactly one bucket; there is always one bucket at least (the flag's)."""
    buckets: list[list[int]] = []
    current: list[int] = []
    held = 0
    for i in reversed(range(len(sizes))):
        current.append(i)
        held += 4 * sizes[i]
        if held >= cap_bytes:
            buckets.append(current)
            current, held = [], 0
    if current or not buckets:
        buckets.append(current)
    return buckets


def rank_device(device: str, local_rank: int) -> str:
    """One device per rank: any CUDA device becomes cuda:LOCAL_RANK; the CPU stays the CPU."""
    return f"cuda:{local_rank}" if device.startswith("cuda") else device


def setup(device: str) -> tuple[Dist, str]:
    """Join the process group torchrun describes (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR/PORT):
    gloo on the CPU, NCCL on CUDA, collectives failing after NAVI_DIST_TIMEOUT_S. Returns this rank's
    Dist and device. Without a launcher, or with WORLD_SIZE 1: Dist() and `device`, no process group."""
    limit = timeout_from_env()
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist(timeout_s=limit), device
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    dev = rank_device(device, local)
    if dev.startswith("cuda"):
        if local >= torch.cuda.device_count():
            raise ValueError(
                f"rank {rank} needs GPU cuda:{local} but this machine has {torch.cuda.device_count()} "
                "(one rank per GPU: lower --nproc / --nproc-per-node)"
            )
        os.environ.setdefault("TORCH_NCCL_ASYNC_ERROR_HANDLING", "1")
        torch.cuda.set_device(dev)
    backend = "nccl" if dev.startswith("cuda") else "gloo"
    tdist.init_process_group(backend, timeout=timedelta(seconds=limit))
    return Dist(rank, world, local, limit), dev


def leave(d: Dist, code: int = 0) -> None:
    """End a rank process of a data-parallel run now, with exit status `code`, once its output is
    written (flushed here). Interpreter teardown is skipped: gloo can still abort the process there
    ("terminate called without an active exception", seen under load even after `shutdown`). No-op for
    a single process."""
    if d.active:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def shutdown(d: Dist) -> None:
    """Leave the process group (no-op for a single process). The garbage is collected right away: a
    process group still reachable from a reference cycle would otherwise be freed during interpreter
    shutdown, where gloo aborts the process ("terminate called without an active exception")."""
    if d.active and tdist.is_initialized():
        tdist.destroy_process_group()
        gc.collect()


def collective(d: Dist, what: str, call: Callable[[], T]) -> T:
    """Run one collective; a backend failure becomes a DistError that names the rank and the timeout."""
    try:
        return call()
    except RuntimeError as err:
        raise DistError(
            f"rank {d.rank} of {d.world}: {what} failed: a peer rank died or did not answer within "
            f"{TIMEOUT_ENV}={d.timeout_s:g} s ({str(err).splitlines()[0] if str(err) else type(err).__name__})"
        ) from err


class Solo:
    """The collectives of a single-process run, Sync's twin: each leaves its values as they are, so the
    training loop reads the same for one rank and for N. `reduce` is None: statistics are taken over
    this process's batch directly (RND normaliser, episode statistics), and
    `pools_advantages` is False: the minibatch objective normalises its own advantages."""

    active = False
    pools_advantages = False

    def __init__(self, device: torch.device) -> None:
        self.device = device

    @property
    def reduce(self) -> Callable[[torch.Tensor], torch.Tensor] | None:
        """What sums a tensor over ranks in place, for statistics that pool over ranks: none here."""
        return None

    def sum_(self, t: torch.Tensor) -> torch.Tensor:
        """t itself (the sum over one rank)."""
        return t

    def barrier(self) -> None:
        """Nothing to wait for."""

    def mean(self, values: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """`values` themselves (the mean over one rank)."""
        return values

    def backward(self, loss: torch.Tensor) -> torch.Tensor:
        """loss.backward(); returns () bool: this process's loss is non-finite (the gradients are this
        process's)."""
        loss.backward()
        return ~torch.isfinite(loss)

    def agree(self, interrupt: bool, stop: bool, ext_mean: torch.Tensor) -> tuple[bool, bool, torch.Tensor]:
        """The flags and the mean extrinsic reward as they are."""
        return interrupt, stop, ext_mean

    def broadcast_module(self, module: nn.Module) -> None:
        """Nothing to copy: this replica is the only one."""

    def broadcast_object(self, obj: T) -> T:
        """`obj` itself."""
        return obj

    def gather_object(self, obj: T) -> list[T]:
        """[obj]."""
        return [obj]


class Bucket:
    """Gradients all-reduced together: one flat buffer, allocated once, with a view per parameter; the
    last bucket of a run holds the non-finite-loss flag after its gradients."""

    def __init__(self, params: list[nn.Parameter], device: torch.device, flag: bool) -> None:
        self.params = params
        sizes = [p.numel() for p in params]
        self.size = sum(sizes)
        self.flat = torch.zeros(self.size + int(flag), device=device)  # (n [+ 1],) float32 grads [, flag]
        self.views = list(self.flat[: self.size].split(sizes)) if sizes else []  # each (numel_i,) float32
        self.ready = 0  # gradients counted in during this backward
        self.work: tdist.Work | None = None  # its all-reduce in flight


class Sync:
    """The collectives of one data-parallel run on `device`. The gradient buckets (`bucket_mb` MiB each,
    default NAVI_DIST_BUCKET_MB) are allocated once, with a hook on every parameter of `params`; they
    act only inside `backward`. With `timers` (training's StageTimers) every wait for a collective is
    timed as the stage "sync". A single-process run uses its twin Solo, whose every call leaves the
    values as they are."""

    active = True
    pools_advantages = True

    def __init__(
        self,
        d: Dist,
        params: list[nn.Parameter],
        device: torch.device,
        timers: Callable[[str], AbstractContextManager[None]] | None = None,
        bucket_mb: float | None = None,
    ) -> None:
        if not d.active:
            raise ValueError("Sync needs a process group (world size > 1)")
        if any(p.dtype != torch.float32 for p in params):
            raise ValueError("the gradient buckets hold float32 parameters only")
        mb = bucket_mb_from_env() if bucket_mb is None else bucket_mb
        if mb <= 0:
            raise ValueError(f"bucket_mb must be positive, got {mb}")
        self.d, self.params, self.device, self.timers = d, params, device, timers
        plan = bucket_plan([p.numel() for p in params], int(mb * 2**20))
        self.buckets = [
            Bucket([params[i] for i in idx], device, k == len(plan) - 1) for k, idx in enumerate(plan)
        ]
        self.flag = self.buckets[-1].flat[-1:]  # (1,) float32 view: ranks whose loss is non-finite
        self.armed = False  # hooks act only inside backward()
        self.next = 0  # the next bucket to launch
        self.hooks = [
            p.register_post_accumulate_grad_hook(functools.partial(self._ready, k))
            for k, bucket in enumerate(self.buckets)
            for p in bucket.params
        ]
        self.lagged: tuple[tdist.Work | None, torch.Tensor] | None = None  # the normaliser's sums

    def _timed(self) -> AbstractContextManager[None]:
        return self.timers("sync") if self.timers is not None else nullcontext()

    def _all_reduce(self, what: str, t: torch.Tensor, op: Any = tdist.ReduceOp.SUM) -> torch.Tensor:
        with self._timed():
            collective(self.d, what, lambda: tdist.all_reduce(t, op=op))
        return t

    def _launch(self, what: str, t: torch.Tensor) -> tdist.Work:
        return cast(tdist.Work, collective(self.d, what, lambda: tdist.all_reduce(t, async_op=True)))

    def _wait(self, what: str, work: tdist.Work) -> None:
        with self._timed():
            collective(self.d, what, work.wait)

    @property
    def reduce(self) -> Callable[[torch.Tensor], torch.Tensor] | None:
        """What sums a tensor over ranks in place (sum_), for statistics that pool over ranks."""
        return self.sum_

    def sum_(self, t: torch.Tensor) -> torch.Tensor:
        """Sum t over ranks, in place; returns t."""
        return self._all_reduce("all-reduce", t)

    def sum_kept(self, t: torch.Tensor) -> torch.Tensor:
        """Sum t over ranks in place, waited for, and keep it as the normaliser's last pooled sums:
        lagged_previous hands it back at the next step (a run's first step, which has no earlier sums,
        pools its own). Returns t."""
        self._wait("normaliser all-reduce", self._launch("normaliser all-reduce", t))
        self.lagged = (None, t)
        return t

    def lagged_previous(self) -> torch.Tensor | None:
        """The sums last handed to sum_kept or launch_lagged, summed over ranks (waited for now); None
        before the first. A CUDA wait holds back the current stream only, not the host."""
        if self.lagged is None:
            return None
        self.settle()
        return self.lagged[1]

    def launch_lagged(self, t: torch.Tensor) -> None:
        """Launch the sum of t over ranks, in place and not waited for: lagged_previous hands it back at
        the next step (every rank makes the same calls in the same order). t must not change until then."""
        self.lagged = (self._launch("normaliser all-reduce", t), t)

    def settle(self) -> None:
        """Wait for the normaliser's sums in flight, if any (lagged_previous still hands them back)."""
        if self.lagged is not None and self.lagged[0] is not None:
            self._wait("normaliser all-reduce", self.lagged[0])
            self.lagged = (None, self.lagged[1])

    def barrier(self) -> None:
        """Wait for every rank (an all-reduce of one number: the same on gloo and NCCL), once nothing of
        this rank is in flight."""
        self.settle()
        self._all_reduce("barrier", torch.zeros(1, device=self.device))  # (1,) float32

    def mean(self, values: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Each () tensor of `values` averaged over ranks (one all-reduce; the same keys on every rank)."""
        names = sorted(values)
        if not names:
            return {}
        stacked = self.sum_(torch.stack([values[k].detach().float() for k in names])) / self.d.world  # (K,)
        return dict(zip(names, stacked.unbind(), strict=True))

    def _ready(self, k: int, param: torch.Tensor) -> None:
        """Post-accumulate-grad hook of a parameter of bucket k: count it in; launch what is complete."""
        if not self.armed:
            return
        self.buckets[k].ready += 1
        while self.next < len(self.buckets):
            bucket = self.buckets[self.next]
            if bucket.ready < len(bucket.params):
                return
            self._send(bucket)
            self.next += 1

    def _send(self, bucket: Bucket) -> None:
        """Pack a bucket's gradients (zeros where a parameter has none) and launch its all-reduce."""
        # multi-tensor copies (a few kernels per bucket, not one per parameter)
        have = [(v, p.grad) for v, p in zip(bucket.views, bucket.params, strict=True) if p.grad is not None]
        missing = [v for v, p in zip(bucket.views, bucket.params, strict=True) if p.grad is None]
        if missing:
            torch._foreach_zero_(missing)
        if have:
            torch._foreach_copy_([v for v, _ in have], [g.reshape(-1) for _, g in have])
        bucket.work = self._launch("gradient all-reduce", bucket.flat)

    def backward(self, loss: torch.Tensor) -> torch.Tensor:
        """loss.backward() with every gradient averaged over ranks: the buckets are all-reduced as their
        gradients come in (the last one carrying the non-finite-loss flag), then waited for in order and
        unpacked, ÷ world size, into the gradients. Returns () bool: some rank's loss was non-finite (the
        same on every rank)."""
        self.flag.copy_((~torch.isfinite(loss.detach())).float().reshape(1))
        for bucket in self.buckets:
            bucket.ready = 0
        self.next = 0
        self.armed = True
        try:
            loss.backward()
        finally:
            self.armed = False
        while self.next < len(self.buckets):  # buckets with a parameter backward did not reach
            self._send(self.buckets[self.next])
            self.next += 1
        for bucket in self.buckets:  # in launch order: an unpack overlaps the later transfers
            self._receive(bucket)
        return self.flag[0] > 0  # () bool

    def _receive(self, bucket: Bucket) -> None:
        """Wait for a bucket's all-reduce and unpack its sums, ÷ world size, into the gradients."""
        if bucket.work is not None:
            self._wait("gradient all-reduce", bucket.work)
            bucket.work = None
        bucket.flat[: bucket.size].div_(self.d.world)
        pairs = zip(bucket.views, bucket.params, strict=True)
        have = [(v, p.grad) for v, p in pairs if p.grad is not None]
        if have:
            torch._foreach_copy_([g for _, g in have], [v.view_as(g) for v, g in have])

    def advantage_moments(self, adv: torch.Tensor, ids: torch.Tensor, chunk: int) -> torch.Tensor:
        """The mean and population std of every minibatch's advantages over the union of the ranks'
        minibatches -> (K, 2) float32, for an epoch's minibatch_ids `ids` (K, M) of sequences of `chunk`
        steps of `adv` (T, N): per-sequence sums, summed per minibatch (float64), then one all-reduce of
        3K numbers for the whole epoch rather than one per minibatch."""
        seq = adv.detach().double().view(adv.shape[0] // chunk, chunk, -1)  # (T/L, L, N) float64
        s1, s2 = seq.sum(1).reshape(-1), seq.pow(2).sum(1).reshape(-1)  # (S,) each, sequence c·N + a
        count = torch.full(
            (len(ids),), float(ids.shape[1] * chunk), dtype=torch.float64, device=adv.device
        )  # (K,)
        sums = self.sum_(torch.stack([s1[ids].sum(1), s2[ids].sum(1), count], dim=1))  # (K, 3) all ranks
        mean, var = moments_of(sums)  # (K,) float64 each
        return torch.stack([mean, var.sqrt()], dim=1).float()  # (K, 2)

    def agree(self, interrupt: bool, stop: bool, ext_mean: torch.Tensor) -> tuple[bool, bool, torch.Tensor]:
        """Once per update: any rank's interrupt / stop flag (max) and the mean extrinsic reward over
        ranks. The flags are read on the host (the one sync of the update)."""
        flags = torch.tensor([float(interrupt), float(stop)], device=self.device)  # (2,) float32
        self._all_reduce("stop-flag all-reduce", flags, tdist.ReduceOp.MAX)
        mean = self.sum_(ext_mean.detach().clone().reshape(1)) / self.d.world  # (1,) float32
        got = flags.tolist()
        return got[0] > 0, got[1] > 0, mean[0]

    def broadcast_module(self, module: nn.Module) -> None:
        """Every parameter and buffer of rank 0's module into this rank's (bool buffers as uint8)."""
        with torch.no_grad():
            for t in [*module.parameters(), *module.buffers()]:
                tmp = t.to(torch.uint8) if t.dtype == torch.bool else t.data  # same shape as t
                self._broadcast(tmp)
                if t.dtype == torch.bool:
                    t.copy_(tmp.bool())

    def _broadcast(self, t: torch.Tensor) -> None:
        collective(self.d, "parameter broadcast", lambda: tdist.broadcast(t, src=0))

    def broadcast_object(self, obj: T) -> T:
        """Rank 0's picklable object."""
        box = [obj]
        collective(self.d, "broadcast", lambda: tdist.broadcast_object_list(box, src=0))
        return box[0]

    def gather_object(self, obj: T) -> list[T]:
        """Every rank's picklable object, in rank order (on every rank)."""
        out: list[Any] = [None] * self.d.world
        collective(self.d, "gather", lambda: tdist.all_gather_object(out, obj))
        return out

    def release(self) -> None:
        """Remove the gradient hooks (the parameters outlive the run)."""
        for hook in self.hooks:
            hook.remove()
        self.hooks.clear()


Collectives = Solo | Sync
"""What the training loop calls across ranks: Sync on several ranks, Solo on one."""


def collectives(
    d: Dist,
    params: list[nn.Parameter],
    device: torch.device,
    timers: Callable[[str], AbstractContextManager[None]] | None = None,
) -> Collectives:
    """Sync for a data-parallel rank (`d.active`), else Solo."""
    return Sync(d, params, device, timers) if d.active else Solo(device)


class StopSignals:
    """SIGINT and SIGTERM only record that they came (no KeyboardInterrupt inside a collective); the
    training loop polls `requested` once per update and the ranks agree on it (max)."""

    def __init__(self) -> None:
        self.received = 0

    def install(self) -> StopSignals:
        """Take over SIGINT and SIGTERM for the rest of the process (main thread only; else a no-op)."""
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self.received = signum

    def requested(self) -> bool:
        return self.received != 0


def replica_digest(module: nn.Module, optimizer: torch.optim.Optimizer) -> dict[str, str]:
    """sha256 of every parameter and buffer (in name order), and of the optimizer state."""

    def digest(items: Iterable[tuple[str, torch.Tensor]]) -> str:
        h = hashlib.sha256()
        for name, t in items:
            h.update(name.encode())
            h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
        return h.hexdigest()

    state = optimizer.state_dict()["state"]
    opt_items = [
        (f"{i}.{k}", v) for i in sorted(state) for k, v in sorted(state[i].items()) if torch.is_tensor(v)
    ]
    return {"model": digest(sorted(module.state_dict().items())), "optimizer": digest(opt_items)}


def write_debug(d: Dist, module: nn.Module, optimizer: torch.optim.Optimizer, step_id: int) -> Path | None:
    """With NAVI_DIST_DEBUG_DIR set: rank<r>.json there with this replica's hashes; else nothing."""
    folder = os.environ.get(DEBUG_DIR_ENV, "")
    if not folder:
        return None
    path = Path(folder) / f"rank{d.rank}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    body = {"rank": d.rank, "world": d.world, "step_id": step_id, **replica_digest(module, optimizer)}
    path.write_text(json.dumps(body))
    return path


def strip_option(argv: list[str], name: str) -> list[str]:
    """argv without `name VALUE` / `name=VALUE`."""
    out: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg == name:
            skip = True
        elif not arg.startswith(f"{name}="):
            out.append(arg)
    return out


def entry_argv() -> list[str]:
    """How torchrun starts this program again: `-m navi`, or the script that is running (e.g.
    tests/navi_device.py on a GPU host without the service packages)."""
    script = Path(sys.argv[0])
    if script.suffix == ".py" and script.name != "__main__.py":
        return [str(script)]
    return ["-m", "navi"]


def torchrun_argv(nproc: int, args: list[str], entry: list[str] | None = None) -> list[str]:
    """`python -m torch.distributed.run --standalone --nproc-per-node N <entry> args`; the entry is this
    program (entry_argv) unless given (e.g. ["-m", "some.module"])."""
    return [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc-per-node={nproc}",
        *(entry_argv() if entry is None else entry),
        *args,
    ]


def relaunch(
    nproc: int, args: list[str], env: dict[str, str] | None = None, entry: list[str] | None = None
) -> int:
    """Run `args` (this program's arguments without --nproc, or those of `entry`) on nproc ranks through
    torchrun; returns its exit code. Ctrl+C reaches torchrun and the ranks from the terminal, so this
    process ignores SIGINT while it waits; SIGTERM is passed on to torchrun, which passes it on to the
    ranks."""
    proc = subprocess.Popen(torchrun_argv(nproc, args, entry), env=env)
    main = threading.current_thread() is threading.main_thread()
    previous = {}
    if main:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, signal.SIG_IGN)
        previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, lambda s, f: proc.send_signal(s))
    try:
        return proc.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
