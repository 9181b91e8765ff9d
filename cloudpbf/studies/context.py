"""What every study shares: output folder, run cache, scale, and where runs execute.

Timing studies (Table 1, scaling) run their specs one after another in this process.  The others
(compare, sweep, stress) send every missing run to dask.distributed: a LocalCluster of worker
processes by default (one per CPU core, each with one OpenMP/XLA thread; on a GPU machine one
worker per visible GPU, pinned with CUDA_VISIBLE_DEVICES), or an existing scheduler
(``--scheduler tcp://host:8786``) to spread a study over many machines.  Each task is one RunSpec;
workers write into the run cache, which must then be a path every worker sees (a shared
filesystem), and send back a small summary dict.  Runs already in the cache are not sent at all.
``--scheduler inline`` runs the missing specs one by one in this process, without dask (debugging).

``--gpus all`` (or a count N) asks for dask-cuda's ``LocalCUDACluster`` instead: one worker per GPU (all
visible GPUs, or the first N), one run at a time on each, every worker pinned to its GPU through
CUDA_VISIBLE_DEVICES (dask-cuda gives worker i the list rotated to start at GPU i, and the solver
uses the first visible device).  It needs the ``multigpu`` extra (dask-cuda) and a visible GPU;
otherwise the command ends with exit code 2 naming ``--gpus``.
"""
from __future__ import annotations

import importlib.util
import logging
import os
import re
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from cloudpbf import runs
from cloudpbf.solvers import ParticleAdapter
from cloudpbf.store.identity import REPO_ROOT
from cloudpbf import environment
from cloudpbf.studies.scales import Scale
from cloudpbf_io.progress import progress_bar as tqdm

__all__ = ["StudyContext", "StudyError", "GpuError", "INLINE", "parse_gpus", "select_gpus", "visible_gpus",
           "cuda_cluster"]

INLINE = "inline"


def has_distributed() -> bool:
    """Whether dask's distributed (the local and remote clusters) is installed."""
    return importlib.util.find_spec("distributed") is not None


class StudyError(RuntimeError):
    """Some runs of a study failed (not instabilities: those are results).  Finished runs stay cached."""


class SchedulerError(ValueError):
    """The --scheduler address is malformed or no dask scheduler answers there."""


class GpuError(ValueError):
    """--gpus cannot be honoured: a bad value, no GPU, fewer GPUs than asked, dask-cuda missing, or an
    option that contradicts it."""


GPUS_ALL = "all"


def parse_gpus(text) -> str | int | None:
    """--gpus: 'all' or a positive count; None stays None (GpuError otherwise)."""
    if text is None:
        return None
    value = str(text).strip().lower()
    if value == GPUS_ALL:
        return GPUS_ALL
    if re.fullmatch(r"[0-9]{1,4}", value) and 1 <= int(value) <= 1024:      # ASCII digits only ("²" is no count)
        return int(value)
    shown = value if len(value) <= 40 else value[:37] + "..."
    raise GpuError(f"'{shown}': expected 'all' or a number of GPUs (1, 2, ...)")


def visible_gpus() -> list[str]:
    """The GPUs this process may use: the entries of CUDA_VISIBLE_DEVICES when set, else 0..n-1 of
    nvidia-smi's devices (none without a driver)."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [v.strip() for v in visible.split(",") if v.strip() and v.strip() != "-1"]
    return [str(i) for i in range(environment.gpu_count())]


def select_gpus(request: str | int, visible: list[str]) -> list[str]:
    """The devices for `--gpus request` among `visible` ('all': every one; N: the first N)."""
    if not visible:
        raise GpuError(f"{request}: no CUDA GPU is visible here (nvidia-smi finds none, or "
                       "CUDA_VISIBLE_DEVICES hides them); leave --gpus out to run on the CPU")
    if request == GPUS_ALL:
        return list(visible)
    if request > len(visible):
        raise GpuError(f"{request}: only {len(visible)} GPU(s) visible ({','.join(visible)})")
    return list(visible[:request])


def cuda_cluster(devices: list[str], env: dict):
    """dask-cuda's LocalCUDACluster with one single-threaded worker per device (the default factory
    of StudyContext.cuda_cluster_factory)."""
    try:
        from dask_cuda import LocalCUDACluster  # multigpu extra (dask_cuda)
    except ImportError:
        raise GpuError("needs dask-cuda, which is not installed: pip install 'cloudpbf[multigpu]'") from None
    return LocalCUDACluster(CUDA_VISIBLE_DEVICES=",".join(devices), n_workers=len(devices), threads_per_worker=1,
                            dashboard_address=None, silence_logs=logging.CRITICAL, env=env)


_SCHEDULER = re.compile(r"(?:(tcp|tls|ucx|ws|wss)://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})/?")
SCHEDULER_TIMEOUT_S = float(os.environ.get("CLOUDPBF_SCHEDULER_TIMEOUT", "10"))


def check_scheduler_address(address: str) -> str:
    """'inline' or a dask scheduler address ([tcp|tls|ucx|ws|wss://]host:port); SchedulerError otherwise."""
    if address == INLINE:
        return address
    m = _SCHEDULER.fullmatch(address) if isinstance(address, str) else None     # fullmatch: no trailing newline
    if not m or not 1 <= int(m.group(3)) <= 65535:
        shown = repr(address)[1:-1] if isinstance(address, str) else repr(address)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise SchedulerError(f"'{shown}': expected 'inline' or a dask scheduler address such as "
                             f"tcp://host:8786 (scheme tcp, tls, ucx, ws or wss; port 1-65535)")
    return address


def _where(exc: BaseException) -> str:
    """' (at file:line in function)' of the innermost frame of an exception's traceback, if it has one."""
    frames = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ else []
    if not frames:
        return ""
    f = frames[-1]
    return f" (at {f.filename}:{f.lineno} in {f.name})"


def xla_single_thread_flags(existing: str | None = None) -> str:
    """XLA_FLAGS for a single-threaded jax worker: the existing flags plus ``--xla_cpu_multi_thread_eigen=false``.

    XLA reads only ``--``-prefixed flags from XLA_FLAGS.  The often-quoted ``intra_op_parallelism_threads=1``
    is no XLA flag: without ``--`` XLA skips it silently, with ``--`` it aborts the process ("Unknown flag in
    XLA_FLAGS"), so it is not set (and dropped from `existing`, where it would do nothing).  The worker's
    OpenMP threads are set by OMP_NUM_THREADS."""
    flags = [f for f in (existing or "").split() if f.startswith("--")]
    if not any(f.startswith("--xla_cpu_multi_thread_eigen") for f in flags):
        flags.append("--xla_cpu_multi_thread_eigen=false")
    return " ".join(flags)


def _worker_env(threads: int) -> dict:
    env = {"OMP_NUM_THREADS": str(threads),
           "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    if threads == 1:
        env["XLA_FLAGS"] = xla_single_thread_flags(os.environ.get("XLA_FLAGS"))
    if os.environ.get("CLOUDPBF_RUNS"):
        env["CLOUDPBF_RUNS"] = os.environ["CLOUDPBF_RUNS"]
    return env


def local_cluster(n_workers: int, gpus: list[str] | None = None):
    """A dask cluster on this machine: `n_workers` processes, or one per GPU index in `gpus`."""
    # harness extra (distributed)
    from distributed import LocalCluster, Nanny, Scheduler, SpecCluster
    cores = os.cpu_count() or 1
    if gpus:
        threads = max(1, cores // len(gpus))
        workers = {f"gpu-{g}": {"cls": Nanny, "options": {
            "nthreads": 1, "silence_logs": logging.CRITICAL,
            "env": {**_worker_env(threads), "CUDA_VISIBLE_DEVICES": g}}} for g in gpus}
        return SpecCluster(workers=workers, scheduler={"cls": Scheduler, "options": {"dashboard_address": None}},
                           silence_logs=logging.CRITICAL)
    threads = max(1, cores // n_workers)
    return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None,
                        env=_worker_env(threads), silence_logs=logging.CRITICAL)


@dataclass
class StudyContext:
    """Options shared by the studies (the CLI's common options)."""
    out: Path
    scale: Scale
    runs_root: Path = field(default_factory=runs.default_root)
    backend: str = "auto"
    workers: int | None = None
    scheduler: str | None = None
    quiet: bool = False
    gpus: str | int | None = None
    cuda_cluster_factory: object = None      # (devices, env) -> a dask cluster; None: dask-cuda's

    def __post_init__(self):
        self.out = Path(self.out).resolve()
        self.runs_root = Path(self.runs_root).resolve()
        if self.workers is not None and not 1 <= int(self.workers) <= 4096:
            raise ValueError(f"workers = {self.workers}: expected an integer in [1, 4096]")
        if self.scheduler is not None:
            check_scheduler_address(self.scheduler)
        self.gpus = parse_gpus(self.gpus)
        if self.gpus is not None:
            if self.scheduler is not None:
                raise GpuError(f"{self.gpus}: --gpus starts its own cluster; it cannot be combined with --scheduler")
            if self.workers is not None:
                raise GpuError(f"{self.gpus}: --gpus sets one worker per GPU; leave --workers out")
            if self.backend == "cpu":
                raise GpuError(f"{self.gpus}: --gpus runs the particle solver on CUDA; --backend cpu contradicts it")
        self._client = None
        self._cluster = None

    # ---- outputs -------------------------------------------------------------------------------
    @property
    def data(self) -> Path:
        return self.out / "data"

    @property
    def commit(self) -> str:
        return environment.commit()

    def say(self, message: str) -> None:
        if not self.quiet:
            print(message, file=sys.stderr, flush=True)

    def particle_backend(self) -> str:
        return ParticleAdapter.resolve_backend(self.backend)

    # ---- running -------------------------------------------------------------------------------
    def run_serial(self, specs: list[runs.RunSpec], label: str) -> list[runs.RunResult]:
        """Run specs here, one after another (timing studies: nothing else competes for the device)."""
        out = []
        for i, spec in enumerate(specs):
            cached = runs.cached_result(spec, self.runs_root)
            if cached is None:
                self.say(f"{label}: run {i + 1}/{len(specs)}: {spec.solver} {spec.scene.name}")
            out.append(cached or runs.execute(spec, self.runs_root, quiet=self.quiet))
        return out

    def run_parallel(self, specs: list[runs.RunSpec], label: str) -> list[runs.RunResult]:
        """Run the specs the cache lacks on the dask cluster; results in the order of `specs`."""
        keys = [spec.key() for spec in specs]
        unique = dict(zip(keys, specs))
        done = {}
        for key, spec in unique.items():
            hit = runs.cached_result(spec, self.runs_root)
            if hit is not None:
                done[key] = hit
        missing = [k for k in unique if k not in done]
        failures = []
        if missing:
            self.say(f"{label}: {len(done)} runs cached, {len(missing)} to run on {self.cluster_description()}")
            bar = tqdm(total=len(missing), desc=label, unit="run", disable=True if self.quiet else None)
            for key, outcome in self._execute({k: unique[k] for k in missing}, label):
                if isinstance(outcome, BaseException):  # a crashed run: report it, keep the others
                    spec = unique[key]
                    failures.append(f"{spec.solver} {spec.scene.name} seed {spec.seed} "
                                    f"({spec.directory(self.runs_root, key)}): {type(outcome).__name__}: {outcome}"
                                    f"{_where(outcome)}")
                else:
                    done[key] = runs.RunResult.load(outcome["path"])
                bar.update(1)
            bar.close()
        if failures:
            raise StudyError(f"{label}: {len(failures)} of {len(unique)} runs failed (finished runs are cached; "
                             "rerun to retry):\n  " + "\n  ".join(failures))
        return [done[k] for k in keys]

    def _execute(self, specs: dict, label: str):
        """Yield (key, summary dict or the exception) for every spec, as each finishes."""
        root = str(self.runs_root)
        if self.runs_inline():
            for key, spec in specs.items():
                try:
                    yield key, runs.execute_summary(spec, root)
                except Exception as exc:
                    yield key, exc
            return
        from distributed import as_completed  # harness extra (distributed)
        client = self.client()
        futures = {client.submit(runs.execute_summary, spec, root, pure=False, key=f"{label}-{spec.solver}-{key[:16]}"): key
                   for key, spec in specs.items()}
        for future in as_completed(futures):
            try:
                yield futures[future], future.result()
            except Exception as exc:
                yield futures[future], exc

    def gpu_devices(self) -> list[str]:
        """The devices of --gpus (GpuError when they cannot be had); [] without --gpus."""
        if self.gpus is None:
            return []
        return select_gpus(self.gpus, visible_gpus())

    def check_gpus(self) -> None:
        """Fail now, before any run, when --gpus cannot be honoured (no GPU, too few, no dask-cuda)."""
        if self.gpus is None:
            return
        self.gpu_devices()
        if self.cuda_cluster_factory is None:
            try:
                # multigpu extra (dask_cuda)
                import dask_cuda  # noqa: F401
            except ImportError:
                raise GpuError(f"{self.gpus}: needs dask-cuda, which is not installed: "
                               "pip install 'cloudpbf[multigpu]'") from None

    def n_workers(self) -> int:
        if self.gpus is not None:
            return len(self.gpu_devices())
        if self.workers:
            return int(self.workers)
        gpus = self._gpus()
        return len(gpus) if gpus else (os.cpu_count() or 1)

    def _gpus(self) -> list[str]:
        """GPU indices for one worker each, when the particle runs go to CUDA."""
        if self.scheduler or self.particle_backend() != "cuda":
            return []
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        if visible:
            return [v.strip() for v in visible.split(",") if v.strip()]
        return [str(i) for i in range(max(1, environment.gpu_count()))]

    def runs_inline(self) -> bool:
        """Runs in this process: --scheduler inline, or no dask installed and no cluster asked for."""
        return self.scheduler == INLINE or (self.scheduler is None and self.gpus is None and not has_distributed())

    def cluster_description(self) -> str:
        if self.scheduler == INLINE:
            return "this process (inline, no dask)"
        if self.runs_inline():
            return "this process (inline: dask's distributed is not installed)"
        if self.scheduler:
            return f"the dask scheduler at {self.scheduler}"
        if self.gpus is not None:
            devices = self.gpu_devices()
            return f"a dask-cuda cluster of {len(devices)} GPU workers (GPUs {','.join(devices)})"
        gpus = self._gpus()
        if gpus and not self.workers:
            return f"a local dask cluster of {len(gpus)} GPU workers"
        return f"a local dask cluster of {self.n_workers()} workers"

    def client(self):
        if self._client is None:
            if not has_distributed():
                raise SchedulerError("a dask cluster (--scheduler ADDRESS or --gpus) needs dask's distributed, "
                                 "which is not installed (a dependency of cloudpbf: pip install distributed), or run "
                                 "with --scheduler inline")
            from distributed import Client  # harness extra (distributed)
            if self.scheduler:
                # dask moves pickles between the client, the scheduler and the workers: a remote
                # scheduler must be one you trust (see docs/harness.md).
                try:
                    self._client = Client(self.scheduler, timeout=SCHEDULER_TIMEOUT_S)
                except (OSError, TimeoutError, ValueError) as exc:
                    why = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
                    raise SchedulerError(f"no dask scheduler answered at {self.scheduler} within "
                                         f"{SCHEDULER_TIMEOUT_S:g} s ({why})") from None
                except Exception as exc:  # noqa: BLE001  (a peer that is no dask scheduler: a frame too
                    # large to allocate (MemoryError), a message that does not decode, a protocol error)
                    why = (str(exc).splitlines() or [""])[0][:160] or type(exc).__name__
                    raise SchedulerError(f"the peer at {self.scheduler} does not answer as a dask scheduler "
                                         f"({type(exc).__name__}: {why})") from None
            elif self.gpus is not None:
                devices = self.gpu_devices()
                cores = os.cpu_count() or 1
                factory = self.cuda_cluster_factory or cuda_cluster
                self._cluster = factory(devices, _worker_env(max(1, cores // len(devices))))
                self._client = Client(self._cluster)
            else:
                gpus = [] if self.workers else self._gpus()
                self._cluster = local_cluster(self.n_workers(), gpus)
                self._client = Client(self._cluster)
        return self._client

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
