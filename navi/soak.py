"""`navi soak`: the local stack under a seeded schedule of overlapping faults, then a table of what held.

The stack is `navi stack`'s five processes (router, compiler, env, learner, auditor) on loopback, in a
folder of their own, training on a small procedural corpus on the CPU. While it trains, a seeded
schedule injects faults, several at once:

- kill: SIGKILL of one service's process group, then a restart with the same command (each service in
  turn); the learner resumes from its newest checkpoint that loads (`--resume-latest`);
- pause: SIGSTOP of the env for longer than a step request's time-out, then SIGCONT;
- garbage: random bytes and wrong-schema messages on every topic a service subscribes to;
- bad REST: malformed, unauthorised and oversized requests to the control plane;
- promote: promotions and rollbacks of the newest checkpoints while the learner writes them;
- bomb: a compile job whose source is an archive bomb (a member far over the worker's size cap).

A brain thread steps the env service all along (the way an external brain does), and a monitor samples
each process's resident memory, open file descriptors and threads. Faults that would blur a count are
serialised by per-service locks (a garbage burst and a kill of the same service never overlap; a router
kill waits for everything else); the rest overlap freely. At the end: the checks below, as a table and
as JSON (soak.json in the soak folder); exit status 1 when a check fails.
"""

from __future__ import annotations

import http.client
import json
import os
import random
import signal
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

from navi.stack import ORDER, StackConfig, is_running, pid_file, service_specs, start, stop_all

FAULTS = ("kill", "pause", "garbage", "bad_rest", "promote", "bomb")
TOKEN = "soak-token"


@dataclass(frozen=True)
class SoakConfig:
    """A soak run."""

    minutes: float = 5.0
    """How long faults are injected (the stack's start and the final checks come on top)."""
    seed: int = 0
    """Seed of the fault schedule and of the garbage payloads."""
    root: Path = Path("artifacts/soak")
    """The soak's folder: the stack's logs and pid files, runs, models, corpus, soak.json."""
    base_port: int = 17447
    """Router port; the control plane, dashboard and the /metrics ports take the next four."""
    fault_gap_s: float = 8.0
    """Mean seconds between the starts of two faults (exponential gaps: several overlap)."""
    pause_s: float = 12.0
    """How long the env stays stopped: longer than the brain's step time-out."""
    step_timeout_s: float = 5.0
    """The brain's step request time-out."""
    checkpoint_every: int = 512
    """Learner env steps between checkpoints: the most a learner kill may roll back (plus a rollout)."""
    actors: int = 2
    """Learner actors."""
    token_wait_s: float = 120.0
    """A restarted service's liveliness token must be back within this."""
    rss_slope_mb: float = 48.0
    """Bound on resident memory growth per restart of a service (MB), fitted over its restarts."""
    fd_slope: float = 4.0
    """Bound on open file descriptor growth per restart of a service, fitted over its restarts."""
    settle_s: float = 20.0
    """A process's age at which its memory and descriptors are sampled for the across-restarts fit."""


# --------------------------------------------------------------------------------------------------
# The stack under soak


def ports(cfg: SoakConfig) -> dict[str, int]:
    b = cfg.base_port
    return {"router": b, "api": b + 1, "auditor": b + 2, "compiler": b + 3, "env": b + 4}


def stack_config(cfg: SoakConfig) -> StackConfig:
    p = ports(cfg)
    return StackConfig(
        root=cfg.root / "stack",
        router_port=p["router"],
        api_port=p["api"],
        auditor_port=p["auditor"],
        compiler_metrics_port=p["compiler"],
        env_metrics_port=p["env"],
        corpus=cfg.root / "corpus",
        corpus_scenes=2,
        corpus_resolution=64,
        actors=cfg.actors,
        env_actors=2,
        device="cpu",
        total_steps=10**12,
        learner_args=("--checkpoint-every", str(cfg.checkpoint_every), "--resume-latest"),
        compiler_args=("--max-source-mb", "1"),
        cwd=cfg.root,
    )


@dataclass
class Life:
    """One process of a service, from its start to its end."""

    service: str
    pid: int
    started: float
    samples: list[tuple[float, float, int, int]] = field(default_factory=list)
    """(age s, resident MB, open fds, threads)."""


@dataclass
class Record:
    """Everything the soak saw, for the checks."""

    faults: list[dict[str, Any]] = field(default_factory=list)
    lives: list[Life] = field(default_factory=list)
    token_back_s: list[tuple[str, float | None]] = field(default_factory=list)
    learner_restarts: list[dict[str, int]] = field(default_factory=list)
    bad_inputs: list[dict[str, Any]] = field(default_factory=list)
    rest: list[dict[str, Any]] = field(default_factory=list)
    bombs: list[dict[str, Any]] = field(default_factory=list)
    brain_ok: int = 0
    brain_failed: int = 0
    pauses: list[dict[str, Any]] = field(default_factory=list)
    promotions: dict[str, int] = field(default_factory=lambda: {"ok": 0, "refused": 0, "failed": 0})
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, kind: str, **fields: Any) -> None:
        with self.lock:
            self.faults.append({"kind": kind, **fields})


class Soak:
    """The running stack, the fault injectors and the monitor."""

    def __init__(self, cfg: SoakConfig, say: Callable[[str], None]) -> None:
        self.cfg, self.say = cfg, say
        self.stack = stack_config(cfg)
        self.specs = {s.name: s for s in service_specs(self.stack, with_auditor=True)}
        self.env = {
            **os.environ,
            "NAVI_API_TOKEN": TOKEN,
            "NAVI_ZENOH_CONNECT": f"tcp/127.0.0.1:{self.stack.router_port}",
            "NAVI_AZIMUTH_BINS": "32",
            "NAVI_ELEVATION_BINS": "8",
        }
        self.locks = {name: threading.Lock() for name in ORDER}
        self.rec = Record()
        self.stop = threading.Event()
        self.pids: dict[str, int] = {}
        self.rng = random.Random(cfg.seed)
        self.sess: Any = None

    # ---- processes -------------------------------------------------------------------------------

    def launch(self, name: str) -> None:
        state = start(self.specs[name], self.stack.root, self.env, cwd=self.stack.cwd)
        self.pids[name] = state.pid
        with self.rec.lock:
            self.rec.lives.append(Life(name, state.pid, time.monotonic()))

    def kill(self, name: str) -> None:
        pid = self.pids[name]
        with suppress(ProcessLookupError):
            os.killpg(pid, signal.SIGKILL)
        deadline = time.monotonic() + 30.0
        while is_running(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        with suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)

    @contextmanager
    def holding(self, names: tuple[str, ...]) -> Iterator[None]:
        """The services' locks, taken in start order (no two faults wait on each other in a circle)."""
        with ExitStack() as held:
            for name in ORDER:
                if name in names:
                    held.enter_context(self.locks[name])
            yield

    # ---- readings --------------------------------------------------------------------------------

    def url(self, what: str) -> str:
        p = ports(self.cfg)
        return {
            "healthz": f"http://127.0.0.1:{p['api']}/healthz",
            "learner": f"http://127.0.0.1:{p['api']}/metrics",
            "auditor": f"http://127.0.0.1:{p['auditor']}/metrics",
            "dashboard": f"http://127.0.0.1:{p['auditor']}/healthz",
            "compiler": f"http://127.0.0.1:{p['compiler']}/metrics",
            "env": f"http://127.0.0.1:{p['env']}/metrics",
        }[what]

    def health(self) -> dict[str, Any] | None:
        try:
            with urllib.request.urlopen(self.url("healthz"), timeout=2.0) as r:
                body: dict[str, Any] = json.loads(r.read())
                return body
        except (OSError, ValueError, urllib.error.URLError):
            return None

    def scrape(self, service: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float] | None:
        from prometheus_client.parser import text_string_to_metric_families

        try:
            with urllib.request.urlopen(self.url(service), timeout=2.0) as r:
                text = r.read().decode()
        except (OSError, urllib.error.URLError):
            return None
        return {
            (s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text)
            for s in family.samples
        }

    def alive(self) -> set[str]:
        from navi_mesh.liveliness import live_tokens

        try:
            return {t.service for t in live_tokens(self.sess, timeout_s=1.0)}
        except Exception:
            return set()

    def wait(self, pred: Callable[[], bool], timeout_s: float, poll_s: float = 0.25) -> float | None:
        """Seconds until pred() holds, None when it did not within timeout_s."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if pred():
                return time.monotonic() - t0
            time.sleep(poll_s)
        return None

    # ---- the monitor and the brain ---------------------------------------------------------------

    def monitor(self) -> None:
        while not self.stop.wait(2.0):
            now = time.monotonic()
            with self.rec.lock:
                lives = [life for life in self.rec.lives if life.pid == self.pids.get(life.service)]
            for life in lives:
                sample = proc_sample(life.pid)
                if sample is not None:
                    life.samples.append((now - life.started, *sample))

    def brain(self) -> None:
        """Steps the env service as an external brain does, all along."""
        import numpy as np

        from navi_contracts.models import StepRequest, StepResult
        from navi_contracts.topics import STEP
        from navi_mesh.pubsub import request

        i = 0
        while not self.stop.is_set():
            i += 1
            req = StepRequest(
                request_id=f"soak-{i}",
                env_ids=np.array([0, 1], np.int32),
                actions=np.zeros((2, 4), np.float32),
            )
            try:
                request(self.sess, STEP.key, req, StepResult, self.cfg.step_timeout_s)
                self.rec.brain_ok += 1
            except Exception:  # counted: the env or the router may be down on purpose
                self.rec.brain_failed += 1
                self.stop.wait(0.5)
            self.stop.wait(0.2)

    # ---- faults ----------------------------------------------------------------------------------

    def fault_kill(self, name: str) -> None:
        held = ORDER if name == "router" else (name,)
        with self.holding(held):
            before = (self.health() or {}).get("step", 0) if name == "learner" else 0
            self.kill(name)
            entry: dict[str, Any] = {"service": name}
            if name == "learner":
                entry["step_at_kill"] = int(before)
                entry["newest_checkpoint"] = newest_checkpoint_step(self.cfg.root / "artifacts" / "runs")
            time.sleep(self.rng.uniform(0.5, 3.0))
            self.launch(name)
            back = self.wait(lambda: name in self.alive(), self.cfg.token_wait_s)
            with self.rec.lock:
                self.rec.token_back_s.append((name, back))
            if name == "learner":
                resumed = self.wait(
                    lambda: (self.health() or {}).get("phase") == "training", self.cfg.token_wait_s
                )
                health = self.health() or {}
                entry["resumed_at"] = int(health.get("start_step", -1)) if resumed is not None else -1
                with self.rec.lock:
                    self.rec.learner_restarts.append(entry)
            self.rec.add("kill", **entry, token_back_s=back)

    def fault_pause(self) -> None:
        with self.holding(("env",)):
            pid = self.pids["env"]
            os.kill(pid, signal.SIGSTOP)
            self.stop.wait(self.cfg.pause_s)
            failed_before = self.rec.brain_failed
            os.kill(pid, signal.SIGCONT)
            ok_before = self.rec.brain_ok
            back = self.wait(lambda: self.rec.brain_ok > ok_before, 60.0)
            entry = {"paused_s": self.cfg.pause_s, "steps_back_after_s": back, "timeouts": failed_before}
            with self.rec.lock:
                self.rec.pauses.append(entry)
            self.rec.add("pause", **entry)

    def fault_garbage(self, name: str) -> None:
        import zenoh

        from navi_contracts.topics import COMPILE_JOBS, FLOOR_PLAN, OBSERVATIONS, POSES, STEP, TELEMETRY
        from navi_mesh.liveliness import live_tokens

        with self.holding(("router", name)):
            if name == "compiler":
                workers = live_tokens(self.sess, "compiler", 1.0)
                if not workers:
                    return
                topics = [(COMPILE_JOBS, f"{COMPILE_JOBS.key}/{workers[0].instance}", True)]
            elif name == "env":
                topics = [(STEP, STEP.key, True)]
            else:
                topics = [(t, t.key, False) for t in (TELEMETRY, OBSERVATIONS, POSES, FLOOR_PLAN)]
            for topic, key, queryable in topics:
                before = self.decode_errors(name, topic.key)
                if before is None:
                    continue
                payloads = garbage_payloads(self.rng, topic.payload)
                for payload in payloads:
                    if queryable:
                        list(self.sess.get(key, payload=payload, timeout=30.0))
                    else:
                        self.sess.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
                want = before + len(payloads)
                took = self.wait(partial(self.counted_to, name, topic.key, want), 60.0)
                counted = (self.decode_errors(name, topic.key) or 0.0) - before
                entry = {"service": name, "topic": topic.key, "sent": len(payloads), "counted": counted,
                         "counted_after_s": took}  # fmt: skip
                with self.rec.lock:
                    self.rec.bad_inputs.append(entry)
            self.rec.add("garbage", service=name)

    def counted_to(self, service: str, topic: str, want: float) -> bool:
        return (self.decode_errors(service, topic) or 0.0) >= want

    def decode_errors(self, service: str, topic: str) -> float | None:
        samples = self.scrape(service)
        if samples is None:
            return None
        return samples.get(("navi_decode_errors_total", (("topic", topic),)), 0.0)

    def fault_bad_rest(self) -> None:
        api = f"http://127.0.0.1:{ports(self.cfg)['api']}"
        auth = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        cases = [
            ("not json", "/models/promote", b"{not json", auth),
            ("no token", "/models/promote", b'{"checkpoint": "x"}', {"Content-Type": "application/json"}),
            ("wrong token", "/models/promote", b'{"checkpoint": "x"}',
             {"Authorization": "Bearer wrong", "Content-Type": "application/json"}),
            ("unknown checkpoint", "/models/promote", b'{"checkpoint": "/nowhere/x.pt"}', auth),
            ("oversized", "/models/promote", b"", {**auth, "Content-Length": str(64 << 20)}),
            ("wrong schema", "/models/rollback", b'{"alias": 7}', auth),
        ]  # fmt: skip
        with self.holding(("learner",)):
            for name, path, body, headers in cases:
                before = self.metric_sum("learner", "navi_refused_requests_total")
                code = http_post(api + path, body, headers)
                refused = code is not None and 400 <= code < 500
                counted = self.wait(
                    partial(self.grew, "learner", "navi_refused_requests_total", before), 30.0
                )
                entry = {"case": name, "status": code, "refused": refused,
                         "counted": before is not None and counted is not None}  # fmt: skip
                with self.rec.lock:
                    self.rec.rest.append(entry)
            self.rec.add("bad_rest", cases=len(cases))

    def grew(self, service: str, family: str, before: float | None) -> bool:
        return (self.metric_sum(service, family) or 0.0) > (before or 0.0)

    def metric_sum(self, service: str, family: str) -> float | None:
        """The sum of a family's samples on a service's /metrics (None when it does not answer)."""
        samples = self.scrape(service)
        if samples is None:
            return None
        return sum(v for (name, _), v in samples.items() if name == family)

    def fault_promote(self) -> None:
        api = f"http://127.0.0.1:{ports(self.cfg)['api']}"
        auth = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        runs = self.cfg.root / "artifacts" / "runs"
        with self.holding(("learner",)):
            t_end = time.monotonic() + 6.0
            while time.monotonic() < t_end and not self.stop.is_set():
                found = sorted(runs.glob("*/checkpoints/ckpt_step_*.pt"), key=lambda p: p.name)
                if not found:
                    break
                body = json.dumps({"checkpoint": str(found[-1].resolve()), "alias": "champion"}).encode()
                code = http_post(api + "/models/promote", body, auth)
                self.count_promotion(code)
                code = http_post(api + "/models/rollback", json.dumps({"alias": "champion"}).encode(), auth)
                self.count_promotion(code)
            self.rec.add("promote")

    def compile_errors(self) -> float | None:
        samples = self.scrape("compiler")
        return (
            None
            if samples is None
            else samples.get(("navi_compile_jobs_total", (("outcome", "error"),)), 0.0)
        )

    def count_promotion(self, code: int | None) -> None:
        key = "ok" if code == 200 else "refused" if code is not None and 400 <= code < 500 else "failed"
        with self.rec.lock:
            self.rec.promotions[key] += 1

    def fault_bomb(self) -> None:
        from navi_contracts.models import CompileJob, CompileResult
        from navi_contracts.topics import COMPILE_JOBS
        from navi_mesh.liveliness import live_tokens
        from navi_mesh.pubsub import RequestError, request

        bomb = self.cfg.root / "bomb.pk3"
        if not bomb.is_file():
            write_bomb(bomb, 64 << 20)
        with self.holding(("compiler",)):
            workers = live_tokens(self.sess, "compiler", 1.0)
            if not workers:
                return
            errors_before = self.compile_errors()
            out = self.cfg.root / "bomb-out" / f"bomb-{len(self.rec.bombs)}.gmdag"
            job = CompileJob(
                job_id=f"bomb-{len(self.rec.bombs)}", source=str(bomb), output=str(out), resolution=64
            )
            try:
                reply = request(
                    self.sess, f"{COMPILE_JOBS.key}/{workers[0].instance}", job, CompileResult, 120.0
                )
                refused, why = not reply.ok, reply.error or ""
            except RequestError as err:
                refused, why = True, str(err)
            counted = (
                errors_before is not None
                and self.wait(lambda: (self.compile_errors() or 0.0) > errors_before, 30.0) is not None
            )
            entry = {"refused": refused, "why": why[:160], "output_written": out.exists(), "counted": counted}
            with self.rec.lock:
                self.rec.bombs.append(entry)
            self.rec.add("bomb", **entry)

    # ---- the run ---------------------------------------------------------------------------------

    def schedule(self) -> list[tuple[float, str, str]]:
        """(start s, fault, service) over the soak: kills rotate through the services; gaps are
        exponential, so faults overlap."""
        rng = random.Random(self.cfg.seed)
        t, turn = 5.0, 0
        out: list[tuple[float, str, str]] = []
        kinds = ("kill", "garbage", "pause", "kill", "bad_rest", "promote", "kill", "bomb", "garbage")
        while t < 60.0 * self.cfg.minutes:
            kind = kinds[len(out) % len(kinds)]
            name = ""
            if kind == "kill":
                name = ("compiler", "env", "learner", "auditor", "router")[turn % 5]
                turn += 1
            elif kind == "garbage":
                name = rng.choice(("compiler", "env", "auditor"))
            out.append((t, kind, name))
            t += rng.expovariate(1.0 / self.cfg.fault_gap_s)
        return out

    def run(self) -> dict[str, Any]:
        from navi_env.corpus.folder import build_default_corpus
        from navi_mesh.session import SessionConfig, open_new_session

        cfg = self.cfg
        cfg.root.mkdir(parents=True, exist_ok=True)
        self.stack.root.mkdir(parents=True, exist_ok=True)
        if not (self.stack.corpus / "manifest.json").is_file():
            self.say(f"building the soak's corpus in {self.stack.corpus}")
            build_default_corpus(self.stack.corpus, resolution=64, count=2, seed=0)
        for name in ORDER:
            self.launch(name)
            self.say(f"started {name:<9} pid {self.pids[name]}")
        self.sess = open_new_session(
            SessionConfig(connect=(f"tcp/127.0.0.1:{self.stack.router_port}",), connect_timeout_s=60.0)
        )
        up = self.wait(lambda: self.alive() >= set(ORDER), 300.0, poll_s=1.0)
        trained = self.wait(lambda: (self.health() or {}).get("phase") == "training", 300.0, poll_s=1.0)
        if up is None or trained is None:
            self.finish()
            raise SoakError(f"the stack did not come up within 300 s (logs in {self.stack.root})")
        self.say(f"stack up after {up:.1f} s; faults for {cfg.minutes:g} min (seed {cfg.seed})")
        threads = [threading.Thread(target=f, daemon=True) for f in (self.monitor, self.brain)]
        for th in threads:
            th.start()
        t0 = time.monotonic()
        injectors: list[threading.Thread] = []
        for at, kind, name in self.schedule():
            while time.monotonic() - t0 < at:
                time.sleep(0.1)
            injectors_of: dict[str, Callable[[], None]] = {
                "kill": partial(self.fault_kill, name),
                "garbage": partial(self.fault_garbage, name),
                "pause": self.fault_pause,
                "bad_rest": self.fault_bad_rest,
                "promote": self.fault_promote,
                "bomb": self.fault_bomb,
            }
            fn = injectors_of[kind]
            self.say(f"[{time.monotonic() - t0:6.1f} s] {kind} {name}".rstrip())
            th = threading.Thread(target=guarded(fn, self.rec, kind), daemon=True)
            th.start()
            injectors.append(th)
        for th in injectors:
            th.join(timeout=600.0)
        self.say("faults done; final checks")
        answering = {
            name: self.scrape(name) is not None for name in ("compiler", "env", "learner", "auditor")
        }
        answering["dashboard"] = http_get_ok(self.url("dashboard"))
        answering["all tokens"] = self.wait(lambda: self.alive() >= set(ORDER), 60.0) is not None
        self.stop.set()
        for th in threads:
            th.join(timeout=30.0)
        self.finish()
        report = checks(cfg, self.rec, answering)
        (cfg.root / "soak.json").write_text(json.dumps(report, indent=2, default=str))
        return report

    def finish(self) -> None:
        if self.sess is not None:
            self.sess.close()
        stop_all(self.stack.root)


class SoakError(RuntimeError):
    """The soak could not run (the stack did not come up)."""


def guarded(fn: Callable[[], None], rec: Record, kind: str) -> Callable[[], None]:
    """fn, with an exception recorded as a failed fault instead of a silent thread death."""

    def run() -> None:
        try:
            fn()
        except Exception as err:
            rec.add(kind, error=f"{type(err).__name__}: {err}")

    return run


# --------------------------------------------------------------------------------------------------
# Helpers


def proc_sample(pid: int) -> tuple[float, int, int] | None:
    """(resident MB, open file descriptors, threads) of a process from /proc; None when it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    rss_kb = int(fields.get("VmRSS", "0 kB").split()[0])
    return rss_kb / 1024.0, fds, int(fields.get("Threads", "0").strip())


def newest_checkpoint_step(runs: Path) -> int:
    """The step of the newest checkpoint under runs/*/checkpoints that loads (0 when none)."""
    from navi_learner.serving.checkpoint import RUN_CHECKPOINTS, newest_good_checkpoint, read_meta

    path = newest_good_checkpoint(runs, RUN_CHECKPOINTS)
    return 0 if path is None else int(read_meta(path).step_id)


def garbage_payloads(rng: random.Random, model: Any) -> list[bytes]:
    """Random bytes and valid envelopes of the wrong schema for a topic's message model."""
    import msgpack

    from navi_contracts.codec import encode
    from navi_contracts.models import RobotPose, TelemetryEvent

    noise = [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 512))) for _ in range(8)]
    other = (
        TelemetryEvent(key="x", value=1.0, step=0, timestamp=1.0)
        if model is not TelemetryEvent
        else RobotPose(env_id=0, x=0, y=0, z=0, roll=0, pitch=0, yaw=0, timestamp=0)
    )
    name = model.__name__
    return [
        *noise,
        encode(other),
        msgpack.packb({"type": name, "v": 999, "data": {}}),
        msgpack.packb({"type": name, "v": model.schema_version_of(), "data": {}}),
    ]


def write_bomb(path: Path, member_bytes: int) -> None:
    """A .pk3 (zip) whose one map member inflates to member_bytes of zeros (a few KB on disk)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    chunk = bytes(1 << 20)
    with (
        zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as z,
        z.open("maps/bomb.bsp", "w", force_zip64=True) as member,
    ):
        for _ in range(member_bytes // len(chunk)):
            member.write(chunk)


def http_post(url: str, body: bytes, headers: dict[str, str]) -> int | None:
    """The status of a POST, None when nothing answered. A Content-Length header in `headers` is sent as
    given, whatever the body (a client announcing more than the server takes: it must answer at once)."""
    parts = urllib.parse.urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname or "127.0.0.1", parts.port, timeout=30.0)
    try:
        conn.putrequest("POST", parts.path)
        for name, value in {"Content-Length": str(len(body)), **headers}.items():
            conn.putheader(name, value)
        conn.endheaders(body)
        return int(conn.getresponse().status)
    except OSError:
        return None
    finally:
        conn.close()


def http_get_ok(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=5.0) as r:
            return int(r.status) == 200
    except (OSError, urllib.error.URLError):
        return False


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys over xs (0 with fewer than two points)."""
    n = len(xs)
    if n < 2:
        return 0.0
    mx, my = sum(xs) / n, sum(ys) / n
    var = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / var if var > 0 else 0.0


def settled(lives: list[Life], service: str, settle_s: float) -> list[tuple[float, int]]:
    """Per process of a service, in start order: (resident MB, fds) at the first sample past settle_s."""
    out = []
    for life in lives:
        if life.service != service:
            continue
        late = [s for s in life.samples if s[0] >= settle_s]
        if late:
            out.append((late[0][1], late[0][2]))
    return out


# --------------------------------------------------------------------------------------------------
# The checks


@dataclass
class Check:
    name: str
    value: str
    bound: str
    ok: bool


def checks(cfg: SoakConfig, rec: Record, answering: dict[str, bool]) -> dict[str, Any]:
    """The soak's verdicts from what it recorded and the files it left."""
    from navi_learner.serving.checkpoint import CheckpointError, load_checkpoint
    from navi_learner.serving.registry import ModelRegistry, sha256_of

    out: list[Check] = []
    kinds = {k: sum(1 for f in rec.faults if f["kind"] == k) for k in FAULTS}
    errors = [f for f in rec.faults if "error" in f]
    out.append(Check("faults injected", json.dumps(kinds), "every kind at least once",
                     all(v > 0 for v in kinds.values()) and not errors))  # fmt: skip
    for e in errors:
        out.append(Check(f"fault {e['kind']} failed", e["error"][:120], "no fault raises", False))
    # learner restarts: steps lost beyond the rollback to the newest checkpoint
    lost = [
        max(0, r["newest_checkpoint"] - r["resumed_at"]) for r in rec.learner_restarts if r["resumed_at"] >= 0
    ]
    unresumed = sum(1 for r in rec.learner_restarts if r["resumed_at"] < 0)
    out.append(Check("learner steps lost beyond the newest checkpoint", f"{sum(lost)} over {len(lost)} restarts",
                     "0", sum(lost) == 0 and unresumed == 0 and bool(rec.learner_restarts)))  # fmt: skip
    rolled = [r["step_at_kill"] - r["resumed_at"] for r in rec.learner_restarts if r["resumed_at"] >= 0]
    out.append(Check("learner rollback per restart (env steps)", str(max(rolled, default=0)),
                     f"<= checkpoint interval {cfg.checkpoint_every} + a rollout",
                     max(rolled, default=0) <= 2 * cfg.checkpoint_every))  # fmt: skip
    # files on disk
    files = sorted((cfg.root / "artifacts").glob("**/*.pt"))
    bad = []
    for path in files:
        try:
            load_checkpoint(path)
        except CheckpointError as err:
            bad.append(f"{path.name}: {err}")
    out.append(Check("checkpoints and registry files load (weights_only)", f"{len(files) - len(bad)}/{len(files)}",
                     "all", not bad and bool(files)))  # fmt: skip
    registry = ModelRegistry(cfg.root / "artifacts" / "models")
    inconsistent = [e.version for e in registry.list() if sha256_of(registry.root / e.file) != e.sha256]
    aliases_ok = all(v in {e.version for e in registry.list()} for v in registry.aliases().values())
    out.append(Check("registry versions match their files", f"{len(registry.list())} versions, "
                     f"{len(inconsistent)} mismatched", "0 mismatched, every alias known",
                     not inconsistent and aliases_ok))  # fmt: skip
    # leaks across restarts
    for name in ORDER:
        points = settled(rec.lives, name, cfg.settle_s)
        idx = [float(i) for i in range(len(points))]
        rss = slope(idx, [p[0] for p in points])
        fds = slope(idx, [float(p[1]) for p in points])
        out.append(Check(f"{name}: memory, fds per restart", f"{rss:+.1f} MB, {fds:+.2f} fds ({len(points)} lives)",
                         f"<= {cfg.rss_slope_mb:g} MB, <= {cfg.fd_slope:g}",
                         rss <= cfg.rss_slope_mb and fds <= cfg.fd_slope))  # fmt: skip
    backs = [b for _, b in rec.token_back_s]
    worst = max((b for b in backs if b is not None), default=0.0)
    out.append(Check("liveliness token back after a restart", f"max {worst:.1f} s over {len(backs)} restarts",
                     f"<= {cfg.token_wait_s:g} s", all(b is not None for b in backs) and bool(backs)))  # fmt: skip
    out.append(Check("answering at the end", ", ".join(k for k, v in answering.items() if v) or "none",
                     "dashboard, every /metrics, every token", all(answering.values())))  # fmt: skip
    sent = sum(b["sent"] for b in rec.bad_inputs)
    counted = sum(min(b["counted"], b["sent"]) for b in rec.bad_inputs)
    out.append(Check("bad messages counted under their topic", f"{counted:g}/{sent}",
                     "all", sent > 0 and counted == sent))  # fmt: skip
    refused = sum(1 for r in rec.rest if r["refused"] and r.get("counted", False))
    out.append(Check("bad REST requests refused (4xx) and counted", f"{refused}/{len(rec.rest)}", "all",
                     bool(rec.rest) and refused == len(rec.rest)))  # fmt: skip
    held = sum(1 for b in rec.bombs if b["refused"] and not b["output_written"] and b.get("counted", False))
    out.append(Check("archive bombs refused and counted, nothing written", f"{held}/{len(rec.bombs)}",
                     "all", bool(rec.bombs) and held == len(rec.bombs)))  # fmt: skip
    out.append(Check("promotions during checkpoint writes", json.dumps(rec.promotions), "none failed",
                     rec.promotions["failed"] == 0 and rec.promotions["ok"] > 0))  # fmt: skip
    worst_pause = max((p["steps_back_after_s"] or 1e9 for p in rec.pauses), default=0.0)
    out.append(Check("env steps again after SIGCONT", f"max {worst_pause:.1f} s over {len(rec.pauses)} pauses",
                     "<= 60 s", bool(rec.pauses) and worst_pause <= 60.0))  # fmt: skip
    out.append(Check("brain steps (ok / failed while faulted)", f"{rec.brain_ok} / {rec.brain_failed}",
                     "ok > 0", rec.brain_ok > 0))  # fmt: skip
    return {
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()},
        "passed": all(c.ok for c in out),
        "checks": [asdict(c) for c in out],
        "faults": rec.faults,
        "learner_restarts": rec.learner_restarts,
        "bad_inputs": rec.bad_inputs,
        "rest": rec.rest,
        "bombs": rec.bombs,
    }


def table(report: dict[str, Any]) -> str:
    """The checks as a markdown table."""
    lines = ["| check | measured | bound | ok |", "| --- | --- | --- | --- |"]
    for c in report["checks"]:
        lines.append(f"| {c['name']} | {c['value']} | {c['bound']} | {'yes' if c['ok'] else 'NO'} |")
    return "\n".join(lines)


def soak(cfg: SoakConfig, say: Callable[[str], None]) -> dict[str, Any]:
    """Run a soak; returns its report (also in cfg.root / soak.json)."""
    if any(is_running(int(json.loads(p.read_text())["pid"])) for p in (cfg.root / "stack").glob("*.pid")):
        raise SoakError(f"a stack is already running under {cfg.root / 'stack'}")
    for name in ORDER:
        pid_file(cfg.root / "stack", name).unlink(missing_ok=True)
    cfg = replace(cfg, root=cfg.root.resolve())  # the services run in it: every path they get is absolute
    runner = Soak(cfg, say)
    try:
        return runner.run()
    finally:
        runner.stop.set()
        runner.finish()
