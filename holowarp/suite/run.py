"""Running a suite: the output folder, resume, and the two executors (see :mod:`holowarp.suite`).

``"local"``: the objects one after the other, in this process. ``"ray"``: one Ray task per
object (``num_cpus``/``num_gpus`` from the suite), each in a fresh worker process
(``max_calls=1``, so one object's memory is returned before the next starts), submitted to a
local Ray runtime sized to this machine's cores, or to the cluster at ``ray_address``; at
most ``workers`` objects are in flight at once (the rest wait in the driver, so ``workers=1``
runs them one by one). Both call the same :func:`holowarp.suite.work.run_object`; a task that
dies (an out-of-memory kill, a lost node) is retried once by Ray and then recorded as the
object's failure, with the step it was in.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from holowarp.errors import one_line
from holowarp.fileio import atomic_write_json, check_output_dir
from holowarp.progress import bar, say
from holowarp.suite.spec import EXECUTORS, SuiteError, load_suite
from holowarp.suite.summary import write_summary
from holowarp.suite.work import object_folder, read_status, run_object

__all__ = ["run_suite", "check_run_args"]

SUITE_RECORD = "suite.json"


def check_run_args(suite, *, executor: str, ray_address, workers) -> None:
    """Refuse combinations that cannot run, before any work."""
    if executor not in EXECUTORS:
        raise SuiteError(f"--executor {executor!r}: expected one of {', '.join(EXECUTORS)}")
    if workers is not None and workers < 1:
        raise SuiteError(f"--workers {workers}: must be >= 1")
    if executor == "local":
        if ray_address:
            raise SuiteError("--ray-address needs --executor ray")
        if workers is not None and workers > 1:
            raise SuiteError(f"--workers {workers}: the local executor runs one object at a time; use --executor ray")
    if executor == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise SuiteError("--executor ray: Ray is not installed (pip install -e \".[ray]\"), "
                             "or use --executor local") from None
    gpu = [o.name for o in suite.objects if o.num_gpus > 0]
    if gpu and not ray_address:  # on this machine: there must be a GPU
        import torch

        if not torch.cuda.is_available():
            raise SuiteError(f"{suite.source}: object {gpu[0]!r} asks for num_gpus > 0, and this machine has no CUDA "
                             "device (submit to a cluster with --ray-address, or set num_gpus = 0)")
    if executor == "ray" and not ray_address:
        cores = os.cpu_count() or 1
        big = [o for o in suite.objects if o.num_cpus > cores]
        if big:
            raise SuiteError(f"{suite.source}: object {big[0].name!r} asks for num_cpus = {big[0].num_cpus:g}, "
                             f"more than this machine's {cores} cores")


def _prepare_out(out: Path, suite, resume: bool) -> None:
    """Refuse to overwrite a suite run without ``resume``, and to resume one with other settings."""
    record = out / SUITE_RECORD
    if record.is_file():
        if not resume:
            raise SuiteError(f"--out {out}: already holds a suite run ({SUITE_RECORD}); pass --resume to continue it "
                             "or choose another --out")
        try:
            prev = json.loads(record.read_text())
        except ValueError:
            prev = {}
        diff = _diff(prev.get("settings", {}), suite.settings())
        old = {o["name"]: o for o in prev.get("objects", [])}
        diff += [f"objects.{o.name}" for o in suite.objects
                 if o.name in old and _object_key(old[o.name]) != _object_key(_spec_dict(o))]
        if diff:
            raise SuiteError(f"--out {out}: --resume with other settings than that run's ({', '.join(diff[:6])}); "
                             "use another --out")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(record, {"source": suite.source, "settings": suite.settings(),
                               "objects": [_spec_dict(o) for o in suite.objects]})


def _spec_dict(o) -> dict:
    from dataclasses import asdict

    return asdict(o)


def _object_key(d: dict) -> tuple:
    """What an object's results depend on (its resources do not change them)."""
    return tuple(d.get(k) for k in ("mesh", "dataset", "gt", "up_axis"))


def _diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(a) | set(b)):
        x, y = a.get(k), b.get(k)
        if isinstance(x, dict) and isinstance(y, dict):
            out += _diff(x, y, f"{prefix}{k}.")
        elif x != y:
            out.append(f"{prefix}{k}: {x!r} -> {y!r}")
    return out


def _record_crash(out: Path, spec, exc: BaseException) -> dict:
    """A task that died without writing its result: its status says so, with its step."""
    folder = object_folder(out, spec.name)
    st = read_status(folder) or {"name": spec.name, "errors": [], "seconds": {}}
    step = st.get("step") or "start"
    msg = one_line(f"{type(exc).__name__}: {exc}")[:2000]
    st.update(status="failed", step=step, error=msg, errors=list(st.get("errors", [])) + [{"step": step, "error": msg}])
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder / "status.json", st)
    return st


def _report(st: dict, pbar, progress: bool) -> None:
    pbar.update(1)
    secs = sum(st.get("seconds", {}).values())
    tail = f": step {st['step']}: {st['error']}" if st.get("status") == "failed" else ""
    say(f"{st['name']}: {st.get('status')} ({secs:.0f} s){tail}", progress)


def _run_local(todo, settings, out: Path, pbar, progress: bool) -> None:
    for spec in todo:
        _report(run_object(spec, settings, str(out)), pbar, progress)


def _ray_init(ray, ray_address):
    if ray_address:
        ray.init(address=ray_address, logging_level="WARNING", log_to_driver=True)
    else:
        # A new runtime on this machine (never a cluster named by RAY_ADDRESS), one CPU slot per core.
        ray.init(address="local", num_cpus=os.cpu_count() or 1, include_dashboard=False, logging_level="WARNING")


def _run_ray(todo, settings, out: Path, pbar, progress: bool, *, ray_address, workers) -> None:
    import ray

    _ray_init(ray, ray_address)
    try:
        task = ray.remote(max_calls=1, max_retries=1)(run_object)
        pending, running = list(todo), {}
        limit = workers or len(todo)
        while pending or running:
            while pending and len(running) < limit:
                spec = pending.pop(0)
                ref = task.options(num_cpus=spec.num_cpus, num_gpus=spec.num_gpus,
                                   name=f"holowarp-object-{spec.name}").remote(spec, settings, str(out))
                running[ref] = spec
            ready, _ = ray.wait(list(running), num_returns=1)
            for ref in ready:
                spec = running.pop(ref)
                try:
                    st = ray.get(ref)
                except Exception as e:  # noqa: BLE001 -- the worker died; the other objects go on
                    st = _record_crash(out, spec, e)
                _report(st, pbar, progress)
    finally:
        ray.shutdown()


def run_suite(suite_path, out_dir, *, executor: str = "ray", ray_address: str | None = None,
              workers: int | None = None, resume: bool = False, progress: bool = True) -> dict:
    """Run every object of the suite file ``suite_path`` into ``out_dir`` and write
    ``summary.json`` and ``summary.md`` there; returns the summary.

    Args:
        suite_path: the suite file (:mod:`holowarp.suite`).
        out_dir: output folder; one sub-folder per object.
        executor: ``"local"`` (in this process) or ``"ray"``.
        ray_address: with ``"ray"``: an existing cluster's address (``ray start --head``
            prints it); None starts a local runtime sized to this machine's cores.
        workers: the most objects at once (ray; default: as many as the resources allow).
        resume: continue a run in ``out_dir``: objects already done are kept, failed and
            unfinished ones continue from their last finished step.
        progress: a bar over the objects and one status line per finished object.

    Raises:
        SuiteError (an :class:`holowarp.errors.InputError`): a bad suite file, output
            folder or argument, before any work. A failing object never raises.
    """
    t0 = time.perf_counter()
    suite = load_suite(suite_path)
    out = check_output_dir(out_dir)
    check_run_args(suite, executor=executor, ray_address=ray_address, workers=workers)
    _prepare_out(out, suite, resume)
    todo = [o for o in suite.objects if (read_status(object_folder(out, o.name)) or {}).get("status") != "done"]
    pbar = bar(len(suite.objects), initial=len(suite.objects) - len(todo), desc="suite", unit="object",
               progress=progress)
    try:
        if todo and executor == "local":
            _run_local(todo, suite.settings(), out, pbar, progress)
        elif todo:
            _run_ray(todo, suite.settings(), out, pbar, progress, ray_address=ray_address, workers=workers)
    finally:
        pbar.close()
    summary = write_summary(out, suite)
    summary["seconds"] = time.perf_counter() - t0
    return summary
