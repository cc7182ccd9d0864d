"""Where runs execute: in this process one after another (``serial``), or as Ray tasks (``ray``).

An executor takes runs (:meth:`submit`) and hands back finished ones (:meth:`next`) as
``(run, outcome, error)``: the :class:`~lmgs_eval.plans.execute.Outcome` of a run that
completed, or the message of one that failed on every try. Both retry a run that raised
``run.retries`` more times; Ray also retries a run whose worker died (killed, out of memory),
as its ``max_retries`` does. Bad input (an :class:`~lmgs.errors.InputError`) is not retried.
"""

from __future__ import annotations

import os
from collections import deque

from lmgs_eval.errors import UserError
from lmgs_eval.plans.execute import Outcome, execute_run
from lmgs_eval.plans.runs import Run

EXECUTORS = ("serial", "ray")
RAY_MISSING = "--executor ray needs Ray, which is not installed: pip install '.[cluster]' (or pip install 'ray>=2.9')"
# environment a Ray worker gets from the driver: where data and models live, which device
FORWARDED_ENV = ("LMGS_DATA", "LMGS_DEVICE", "XDG_CACHE_HOME", "OMP_WAIT_POLICY")


class SerialExecutor:
    """Runs in this process, in submission order; ``max_parallel`` is 1."""

    name = "serial"
    slots = 1

    def __init__(self) -> None:
        self._queue: deque[tuple[Run, dict[str, str]]] = deque()

    def submit(self, run: Run, known: dict[str, str]) -> None:
        self._queue.append((run, known))

    def next(self) -> tuple[Run, Outcome | None, str | None]:
        run, known = self._queue.popleft()
        error = None
        for _ in range(run.retries + 1):
            try:
                return run, execute_run(run, known), None
            except Exception as exc:  # noqa: BLE001 - any failure of a run is retried, then recorded
                error = f"{exc.__class__.__name__}: {exc}"
        return run, None, error

    def close(self) -> None:
        self._queue.clear()


class RayExecutor:
    """Each run a Ray task with the run's CPU (and GPU) request, spread over the cluster's nodes."""

    name = "ray"

    def __init__(self, address: str | None = None, max_parallel: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise UserError(RAY_MISSING) from None
        self.ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            env = {k: os.environ[k] for k in FORWARDED_ENV if os.environ.get(k)}
            if address is not None:
                _reachable(address)
            try:
                ray.init(address=address, include_dashboard=False, logging_level="ERROR", log_to_driver=False,
                         runtime_env={"env_vars": env} if env else None)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                why = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
                if address is None:
                    raise UserError(f"--executor ray: Ray could not start or join an instance on this machine ({why})") from None
                raise UserError(f"--address {address}: no Ray cluster there ({why})") from None
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.slots = max_parallel or cpus
        self._remote = ray.remote(_ray_task)
        self._pending: dict = {}

    def submit(self, run: Run, known: dict[str, str]) -> None:
        nodes = [n.get("Resources", {}) for n in self.ray.nodes() if n.get("Alive")]
        for res, need in (("CPU", run.cpus), ("GPU", run.gpus)):
            most = max((n.get(res, 0) for n in nodes), default=0)
            if need > most:
                raise UserError(f"{run.label}: asks for {need:g} {res}(s) a run, and the largest node of the Ray cluster "
                                f"has {most:g}; lower the plan's {res.lower()}s or add a bigger node")
        ref = self._remote.options(num_cpus=run.cpus, num_gpus=run.gpus, max_retries=run.retries,
                                   retry_exceptions=True, scheduling_strategy="SPREAD",
                                   name=f"lmgs-run {run.label}").remote(run, known)
        self._pending[ref] = run

    def next(self) -> tuple[Run, Outcome | None, str | None]:
        (ref,), _ = self.ray.wait(list(self._pending), num_returns=1)
        run = self._pending.pop(ref)
        try:
            return run, self.ray.get(ref), None
        except self.ray.exceptions.RayError as exc:
            cause = getattr(exc, "cause", None)
            msg = f"{cause.__class__.__name__}: {cause}" if cause is not None else str(exc).strip().splitlines()[0]
            return run, None, msg

    def close(self) -> None:
        for ref in self._pending:
            self.ray.cancel(ref, force=True)
        self._pending.clear()
        if self._owns:
            self.ray.shutdown()


def _ray_task(run: Run, known: dict[str, str]) -> Outcome:
    import ray

    out = execute_run(run, known)
    out.node = ray.get_runtime_context().get_node_id()
    return out


def check_executor(name: str, address: str | None = None, max_parallel: int | None = None) -> None:
    """``--executor``, ``--address`` and ``--max-parallel`` checked against each other, with nothing started
    (a dry run checks them as the run does)."""
    if max_parallel is not None and max_parallel < 1:
        raise UserError(f"--max-parallel must be at least 1, got {max_parallel}")
    if name == "serial":
        if address:
            raise UserError("--address names a Ray cluster; it needs --executor ray")
        if max_parallel not in (None, 1):
            raise UserError(f"--max-parallel {max_parallel}: the serial executor runs one at a time; use --executor ray")
        return
    if name != "ray":
        raise UserError(f"--executor {name!r}: expected one of {', '.join(EXECUTORS)}")
    if address is not None:
        _host_port(address)


def make_executor(name: str, address: str | None = None, max_parallel: int | None = None):
    """An executor by name; ``--address`` and ``--max-parallel`` checked against it (:func:`check_executor`)."""
    check_executor(name, address, max_parallel)
    if name == "serial":
        return SerialExecutor()
    return RayExecutor(address, max_parallel)


CONNECT_TIMEOUT_S = 10.0  # how long the cluster's address is given to answer before ray.init is tried


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a Ray address to probe; None for ``auto`` / ``local`` (Ray looks those up itself).

    Raises:
        UserError: the address is neither ``auto``, ``HOST:PORT`` nor ``ray://HOST:PORT``.
    """
    if address in ("auto", "local"):
        return None
    target = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = target.rpartition(":")
    host = host.strip("[]")  # an IPv6 address in brackets
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(f"--address {address}: expected auto or HOST:PORT (the address `ray start --head` prints, "
                        "e.g. 10.0.0.1:6379)")
    return host, int(port)


def _reachable(address: str) -> None:
    """Refuse an address where nothing answers, before ``ray.init``: Ray's own connection retries
    last minutes on an address with no cluster behind it."""
    import socket

    hp = _host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        why = (f"no answer within {CONNECT_TIMEOUT_S:g} s" if isinstance(exc, TimeoutError)
               else (exc.strerror or exc.__class__.__name__).lower())
        raise UserError(f"--address {address}: no Ray cluster there ({hp[0]}:{hp[1]}: {why}; "
                        "start one with `ray start --head`)") from None
