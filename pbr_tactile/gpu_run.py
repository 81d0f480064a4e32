"""The reference's benches on a GPU: one budgeted run, one JSON, the CPU's figures beside it.

Three steps, ``tactile-sim gpu STEP`` (``python3 -m scenes.cli gpu STEP`` where no
``tactile-sim`` script is installed; ``run`` is also ``tactile-sim bench gpu``):

``wheels`` (here, where PyPI answers): ``pbr_tactile.gpu_wheels`` fills ``.whl/`` (git
ignores it) with what the GPU machine lacks for Python 3.12: the project as a wheel (its
subcommands are entry points, found only in an installed distribution), Mitsuba, Dr.Jit,
trimesh, Embree, MuJoCo and the rest, slimmed and LZMA-compressed to fit the 64 MiB that
travels, and the GL loaders for MuJoCo's EGL rendering.

``run`` (there, after ``pip install --no-index --no-deps --target /tmp/site .whl/*.whl``
and ``PYTHONPATH=/tmp/site``): first asks ``variant.choose_variant`` for the variant
(default ``cuda_ad_spectral``); without a CUDA device it prints one line and exits 0
having run nothing. Else it runs each bench of :func:`plan` in a subprocess
(``python3 -m scenes.cli ...``) with ``TACTILE_SIM_MI_VARIANT`` set and
``TACTILE_SIM_CACHE`` in a fresh folder (cold), each stopped at its own budget and none
started once the run's budget (8 minutes by default: a command there may run 10) is
nearly spent; reads each bench's JSON back and writes one JSON: per bench its variant,
device, seconds, key figures (:data:`FIGURES`) and status (``ok``; ``failed``, with why
and the end of its stderr; ``skipped``, for the budget), and the commit.

``merge GPU.json CPU.json --json OUT``: the same benches' entries side by side, with the
ratio GPU / CPU of every figure both have (``run --cpu-json CPU.json`` merges at once).

Where the CPU figures come from: here, by the same command with ``--variant
llvm_ad_spectral`` (and a larger ``--budget-scale``), merged. The other way, the same
run on the GPU machine's CPUs, needs Dr.Jit's LLVM backend there, so LLVM 19: the
Debian package libllvm19 is 25.9 MB and needs libz3-4, libxml2, libedit2 and libffi8
(about 8 MB more) that the image may lack: with the 47 MiB of wheels and the tree's 3 MiB
that is over the 64 MiB that may travel. The CPU figures are therefore this 2-core machine's, not
the GPU machine's 16 cores; the JSON names each side's device.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from scenes.cache import CACHE_ENV

from .gpu_wheels import MANIFEST, git_commit
from .variant import VARIANT_ENV

#: The repository this module is part of (where git can tell the commit).
REPO = Path(__file__).resolve().parents[1]
#: The variant a GPU run renders with.
GPU_VARIANT = "cuda_ad_spectral"
#: What ``variant.choose_variant`` says when there is no GPU: the run then does nothing.
NO_CUDA = "no CUDA device"
#: The run's budget, seconds: a command on the GPU machine may run 10 minutes, and
#: installing the wheels and checking the device take some of them.
RUN_BUDGET_S = 480.0
#: Each bench's own budget, seconds, at ``--budget-scale 1``; the dataset bench's is for
#: a noise target of 5 % and grows as 1 / target (a pass's noise falls as 1 / sqrt(passes)).
BUDGET_S = {"dataset": 90.0, "pbr": 90.0, "calibrate": 120.0, "physical": 300.0}
DATASET_RSE_AT_BUDGET = 0.05
#: A bench is not started with less of the run's budget left than this, seconds.
MIN_START_S = 30.0
#: Seconds a stopped bench gets to end after SIGTERM before SIGKILL.
KILL_GRACE_S = 10.0
#: Lines of stderr kept with a bench that failed.
STDERR_LINES = 12
#: The figures read back from each bench's JSON (dotted paths into it).
FIGURES = {
    "dataset": ("frames_per_hour", "contact_rse_median", "refused", "prepare_seconds", "resolution",
                "local.steady_frames_per_hour", "local.render_seconds_median", "local.contact_rse_max",
                "local.samples", "local.seconds"),
    "pbr": ("seconds_to_2pct", "fluence_seconds_to_2pct", "volpath_seconds_to_2pct", "speedup", "fluence_speedup",
            "fluence_speedup_cached", "variant", "measured.photons_fluence.seconds",
            "measured.photons_fluence.contact_rse", "measured.photons_fluence.no_contact_cache.seconds_to_2pct",
            "measured.volpath.seconds"),
    "calibrate": ("median_relative_error", "share_within_10pct", "seconds_per_case", "heldout_mae_over_noise",
                  "tap_mae_over_noise", "cases", "taps"),
    "physical": ("cases", "top1", "top3", "mean_heldout_shrink", "seconds"),
}
#: The EGL vendor file of NVIDIA's driver on the GPU machine (glvnd may not look there).
NVIDIA_EGL_VENDOR = "/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json"


@dataclass(frozen=True)
class Bench:
    """One sub-run: ``tactile-sim ARGS --json PATH``, stopped after ``budget_s``."""

    name: str
    args: tuple[str, ...]
    budget_s: float
    kind: str  # the key of FIGURES


@dataclass(frozen=True)
class Outcome:
    """How a sub-run ended: its exit status (None: stopped at its budget), its seconds
    and the last lines of its stderr."""

    returncode: int | None
    seconds: float
    stderr_tail: tuple[str, ...]


def plan(rse=(0.05, 0.025), workers: int = 1, pbr_photons: int = 1 << 20, pbr_no_contact_runs: int = 8,
         calibrate_cases: int = 1, calibrate_taps: int = 2, physical: bool = False, physical_cases: int = 1,
         only=None, budget_scale: float = 1.0) -> list[Bench]:
    """The benches of a run, in order, with their budgets (seconds).

    ``only``: names or kinds to keep (``dataset`` keeps every ``dataset_rse_*``); with
    ``physical`` the physical diagnosis comes last (off by default: one case renders 12
    taps three times and diagnoses them).
    """
    for r in rse:
        if not 0 < r < 1:
            raise ValueError(f"--rse must be noise targets in (0, 1), got {r}")
    for name, value in (("--workers", workers), ("--pbr-photons", pbr_photons), ("--calibrate-cases", calibrate_cases),
                        ("--physical-cases", physical_cases)):
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    for name, value in (("--pbr-no-contact-runs", pbr_no_contact_runs), ("--calibrate-taps", calibrate_taps)):
        if value < 0:
            raise ValueError(f"{name} must be >= 0, got {value}")
    if not budget_scale > 0:
        raise ValueError(f"--budget-scale must be > 0, got {budget_scale}")
    benches = [Bench(f"dataset_rse_{r:g}", ("bench", "dataset", "--renderer", "pbr", "--target-rse", f"{r:g}",
                                            "--workers", str(workers)),
                     BUDGET_S["dataset"] * DATASET_RSE_AT_BUDGET / r * budget_scale, "dataset") for r in rse]
    benches.append(Bench("pbr", ("bench", "pbr", "--photons", str(pbr_photons), "--no-contact-runs",
                                 str(pbr_no_contact_runs)), BUDGET_S["pbr"] * budget_scale, "pbr"))
    benches.append(Bench("calibrate", ("calibrate", "benchmark", "--cases", str(calibrate_cases), "--taps",
                                       str(calibrate_taps), "--quiet"), BUDGET_S["calibrate"] * budget_scale,
                         "calibrate"))
    if physical:
        benches.append(Bench("physical", ("diagnose", "benchmark", "--physical", "--cases", str(physical_cases),
                                          "--quiet"), BUDGET_S["physical"] * budget_scale, "physical"))
    if only:
        known = [b.name for b in benches] + sorted({b.kind for b in benches})
        unknown = [o for o in only if o not in known]
        if unknown:
            raise ValueError(f"--only {','.join(unknown)}: not a bench of this run; it has {', '.join(known)}"
                             + ("" if physical else " (and physical, with --physical)"))
        benches = [b for b in benches if b.name in only or b.kind in only]
    return benches


def figures_of(result: dict, kind: str) -> dict:
    """The key figures (FIGURES[kind]) of a bench's JSON, by dotted path; absent ones left out."""
    out = {}
    for path in FIGURES[kind]:
        value = result
        for key in path.split("."):
            value = value.get(key) if isinstance(value, dict) else None
        if value is not None:
            out[path] = value
    return out


def _tail(path: Path, lines: int = STDERR_LINES) -> tuple[str, ...]:
    """The last lines of a log (progress bars' carriage returns split lines too)."""
    try:
        with open(path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 16384))
            text = f.read().decode(errors="replace")
    except OSError:
        return ()
    return tuple(s.rstrip() for s in text.replace("\r", "\n").split("\n") if s.strip())[-lines:]


def run_command(argv: list[str], env: dict, timeout_s: float, logs: Path) -> Outcome:
    """Run ``argv`` in its own session, stdout to ``logs``.out and stderr to ``logs``.err;
    past ``timeout_s`` its whole process group is ended (SIGTERM, then SIGKILL)."""
    t0 = time.monotonic()
    err = Path(f"{logs}.err")
    with open(f"{logs}.out", "wb") as out, open(err, "wb") as errf:
        proc = subprocess.Popen(argv, env=env, stdout=out, stderr=errf, stdin=subprocess.DEVNULL,
                                start_new_session=True)
        try:
            code = proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            code = None
            for sig, grace in ((signal.SIGTERM, KILL_GRACE_S), (signal.SIGKILL, None)):
                try:
                    os.killpg(proc.pid, sig)  # the group this call started, with its workers
                except ProcessLookupError:
                    break
                try:
                    proc.wait(timeout=grace)
                    break
                except subprocess.TimeoutExpired:
                    continue
    return Outcome(code, time.monotonic() - t0, _tail(err))


def bench_env(environ: dict, variant: str, cache: Path) -> dict:
    """A sub-run's environment: the variant, a fresh cache, unbuffered output, and
    NVIDIA's EGL vendor file where the driver has one and nothing names another."""
    env = {**environ, VARIANT_ENV: variant, CACHE_ENV: str(cache), "PYTHONUNBUFFERED": "1"}
    if "__EGL_VENDOR_LIBRARY_FILENAMES" not in env and os.path.exists(NVIDIA_EGL_VENDOR):
        env["__EGL_VENDOR_LIBRARY_FILENAMES"] = NVIDIA_EGL_VENDOR
    return env


def run_benches(benches: list[Bench], variant: str, device: str, work: Path, budget_s: float = RUN_BUDGET_S,
                runner=None, clock=time.monotonic, environ=None) -> dict[str, dict]:
    """Run each bench in turn within ``budget_s`` seconds; ``{name: entry}`` for every one.

    A bench gets ``min(its budget, what is left)``; one past it is stopped and marked
    failed, and one that would start with under MIN_START_S left is marked skipped.
    ``runner(argv, env, timeout_s, logs) -> Outcome`` runs a sub-run (run_command).
    """
    runner = runner or run_command
    environ = dict(os.environ if environ is None else environ)
    start = clock()
    entries = {}
    for bench in benches:
        out = Path(work) / f"{bench.name}.json"
        argv = [sys.executable, "-m", "scenes.cli", *bench.args, "--json", str(out)]
        entry = {"variant": variant, "device": device, "command": "tactile-sim " + " ".join(bench.args),
                 "budget_s": bench.budget_s, "seconds": None, "status": None, "reason": None, "figures": {},
                 "stderr_tail": None}
        entries[bench.name] = entry
        left = budget_s - (clock() - start)
        if left < MIN_START_S:
            entry.update(status="skipped", reason=f"{max(left, 0):.0f} s of the run's {budget_s:.0f} s budget left, "
                                                  f"under the {MIN_START_S:.0f} s a bench needs to start")
            continue
        timeout = min(bench.budget_s, left)
        cache = Path(work) / f"{bench.name}.cache"
        cache.mkdir(parents=True, exist_ok=True)
        outcome = runner(argv, bench_env(environ, variant, cache), timeout, Path(work) / bench.name)
        entry["seconds"] = outcome.seconds
        result = _read_json(out)
        if result is not None:
            entry["figures"] = figures_of(result, bench.kind)  # a stopped bench may have written some cases
        if outcome.returncode is None:
            whose = "its budget" if timeout == bench.budget_s else "what was left of the run's budget"
            entry.update(status="failed", reason=f"stopped at {timeout:.0f} s, {whose}")
        elif outcome.returncode != 0:
            entry.update(status="failed", reason=f"exit status {outcome.returncode}")
        elif result is None:
            entry.update(status="failed", reason=f"exit status 0 but no readable JSON at {out}")
        else:
            entry["status"] = "ok"
        if entry["status"] == "failed":
            entry["stderr_tail"] = list(outcome.stderr_tail)
    return entries


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def device_name(variant: str, run=subprocess.run) -> str:
    """The device a variant renders on: the GPU's name (nvidia-smi), or the CPU's model."""
    if variant.startswith("cuda"):
        try:
            done = run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"],
                       capture_output=True, text=True, timeout=30)
            if done.returncode == 0 and done.stdout.strip():
                return done.stdout.strip().splitlines()[0]
        except (OSError, subprocess.SubprocessError):
            pass
        return "a CUDA device (nvidia-smi did not answer)"
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} CPUs"


def variant_problem(variant: str) -> str | None:
    """Why ``variant`` cannot render here (``variant.choose_variant``'s message), or None."""
    from .variant import VariantError, choose_variant

    try:
        choose_variant(variant)
    except VariantError as exc:
        return str(exc)
    return None


def commit_of(repo: Path, wheels: Path) -> dict:
    """The commit the run's code is: git's, else the wheel set's manifest's (the GPU
    machine's copy of the tree has no .git)."""
    commit, dirty = git_commit(repo)
    if commit is not None:
        return {"commit": commit, "dirty": dirty, "commit_from": "git"}
    manifest = _read_json(Path(wheels) / MANIFEST) or {}
    if manifest.get("commit"):
        return {"commit": manifest["commit"], "dirty": manifest.get("dirty"), "commit_from": f"{wheels}/{MANIFEST}"}
    return {"commit": None, "dirty": None, "commit_from": None}


def load_run(path, what: str) -> dict:
    """A run's JSON (what ``run`` writes), or ValueError naming ``what`` and ``path``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"{what} {path} could not be read: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ValueError(f"{what} {path} is not JSON: {exc}") from None
    if isinstance(data, dict) and "gpu" in data and "cpu" in data:
        raise ValueError(f"{what} {path} is already a merged JSON; give the runs' own JSONs")
    if not isinstance(data, dict) or not isinstance(data.get("benches"), dict) or "variant" not in data:
        raise ValueError(f"{what} {path} is not a run's JSON (expected an object with 'variant' and 'benches', "
                         f"as 'tactile-sim gpu run' writes)")
    return data


def _ratio(a, b):
    if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, (int, float)) or not isinstance(b, (int, float)):
        return None
    return a / b if b else None


def merge(gpu: dict, cpu: dict) -> dict:
    """One JSON of two runs of the same benches: per bench its GPU and CPU entries,
    ``gpu_over_cpu``, the ratio of every numeric figure both have where both are ok, and
    ``same_command`` (a ratio of two sizes of a bench means little)."""
    keys = ("variant", "device", "commit", "dirty", "commit_from", "budget_s", "seconds", "started", "python", "cpus")
    names = list(gpu["benches"]) + [n for n in cpu["benches"] if n not in gpu["benches"]]
    benches = {}
    for name in names:
        g, c = gpu["benches"].get(name), cpu["benches"].get(name)
        ratios = {}
        if g and c and g.get("status") == "ok" and c.get("status") == "ok":
            for key, value in g.get("figures", {}).items():
                r = _ratio(value, c.get("figures", {}).get(key))
                if r is not None:
                    ratios[key] = r
        same = bool(g and c) and g.get("command") == c.get("command")
        benches[name] = {"gpu": g, "cpu": c, "gpu_over_cpu": ratios, "same_command": same}
    return {"what": "the reference's benches on the GPU and on the CPU, the same commands; gpu_over_cpu is each "
                    "figure's GPU value over its CPU value (a rate above 1, or seconds below 1, favour the GPU)",
            "commit": gpu.get("commit"), "same_commit": gpu.get("commit") == cpu.get("commit"),
            "gpu": {k: gpu.get(k) for k in keys}, "cpu": {k: cpu.get(k) for k in keys}, "benches": benches}


def check_output(path, what: str) -> Path:
    """A JSON path to write: its folder must exist, and it must not be a folder."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{what} {path} is a folder; expected a file path to write the JSON to")
    if not path.parent.is_dir():
        raise ValueError(f"{what} {path}: its folder {path.parent} does not exist")
    return path


def _write_json(path: Path, data: dict) -> None:
    """Written whole or not at all, keys in the run's order."""
    from scenes.files import atomic_write_bytes

    atomic_write_bytes(path, (json.dumps(data, indent=2) + "\n").encode())


def cmd_run(args) -> int:
    """``run`` / ``tactile-sim bench gpu``: the benches on ``--variant``, into ``--json``."""
    out = check_output(args.json, "--json")
    cpu = load_run(args.cpu_json, "--cpu-json") if args.cpu_json else None
    if args.budget_s <= 0:
        raise ValueError(f"--budget-s must be > 0, got {args.budget_s}")
    only = [s for s in args.only.split(",") if s] if args.only else None
    benches = plan(rse=args.rse, workers=args.workers, pbr_photons=args.pbr_photons,
                   pbr_no_contact_runs=args.pbr_no_contact_runs, calibrate_cases=args.calibrate_cases,
                   calibrate_taps=args.calibrate_taps, physical=args.physical, physical_cases=args.physical_cases,
                   only=only, budget_scale=args.budget_scale)
    problem = variant_problem(args.variant)
    if problem is not None:
        if args.variant.startswith("cuda") and NO_CUDA in problem:
            print(f"gpu run: no CUDA device here, so nothing was run ({problem})")
            return 0
        from .variant import VariantError

        raise VariantError(problem)
    device = device_name(args.variant)
    budget = args.budget_s * args.budget_scale
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="tactile-gpu-run-") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        print(f"gpu run: {len(benches)} benches on {args.variant} ({device}), {budget:.0f} s budget", flush=True)
        entries = run_benches(benches, args.variant, device, work, budget_s=budget)
    run = {"what": "the reference's benches, each a 'tactile-sim' subprocess with TACTILE_SIM_MI_VARIANT set and "
                   "TACTILE_SIM_CACHE in a fresh folder (cold; Dr.Jit's own kernel cache is the machine's)",
           "variant": args.variant, "device": device, **commit_of(REPO, Path(args.wheels)),
           "python": sys.version.split()[0], "cpus": os.cpu_count(), "budget_s": budget,
           "seconds": time.monotonic() - t0, "started": started, "benches": entries}
    _write_json(out, merge(run, cpu) if cpu is not None else run)
    for name, e in entries.items():
        figures = ", ".join(f"{k} {v:.4g}" for k, v in e["figures"].items() if isinstance(v, float))
        why = f" ({e['reason']})" if e["reason"] else ""
        print(f"{name}: {e['status']}{why}" + (f"; {figures}" if figures else ""))
    print(f"wrote {out}")
    return 0


def cmd_merge(args) -> int:
    out = check_output(args.json, "--json")
    merged = merge(load_run(args.gpu, "GPU.json"), load_run(args.cpu, "CPU.json"))
    _write_json(out, merged)
    print(f"wrote {out}" + ("" if merged["same_commit"] else " (the two runs are of different commits)"))
    return 0


def cmd_wheels(args) -> int:
    from .gpu_wheels import build_wheels

    repo = Path(args.repo)
    manifest = build_wheels(Path(args.dir), repo, gl=not args.no_gl, workers=args.jobs)
    for w in manifest["wheels"]:
        print(f"{w['bytes'] / 2**20:7.2f} MiB  {w['file']}  (was {w['bytes_before'] / 2**20:.2f})")
    for d in manifest["gl_debs"]:
        print(f"{d['bytes'] / 2**20:7.2f} MiB  {d['file']}")
    total, tree = manifest["bytes"], manifest["repo_bytes"]
    print(f"{total / 2**20:.2f} MiB in {args.dir}, {tree / 2**20:.2f} MiB of the tree: "
          f"{(total + tree) / 2**20:.2f} MiB of the {manifest['carry_budget_bytes'] / 2**20:.0f} MiB that may travel")
    if not manifest["fits"]:
        print(f"gpu wheels: error: too big to travel; the biggest: {manifest['wheels'][0]['file']}", file=sys.stderr)
        return 1
    return 0


def _rse_list(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(s) for s in text.split(",") if s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected noise targets separated by commas, e.g. 0.05,0.025; got {text!r}")


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """``run``'s options, but --json (``tactile-sim bench`` adds that itself)."""
    p.add_argument("--variant", default=GPU_VARIANT, help=f"Mitsuba variant (default {GPU_VARIANT}; "
                   "llvm_ad_spectral for the CPU's figures)")
    p.add_argument("--cpu-json", metavar="CPU.json", help="a CPU run's JSON (this command with --variant "
                   "llvm_ad_spectral) to write beside this run's figures")
    p.add_argument("--budget-s", type=float, default=RUN_BUDGET_S, help=f"the whole run's budget, seconds "
                   f"(default {RUN_BUDGET_S:.0f})")
    p.add_argument("--budget-scale", type=float, default=1.0, metavar="K",
                   help="multiply every budget, the run's too (a CPU run takes many times a GPU's)")
    p.add_argument("--only", metavar="NAMES", help="comma-separated benches or kinds: dataset, pbr, calibrate, "
                   "physical, or a name such as dataset_rse_0.05")
    p.add_argument("--rse", type=_rse_list, default=(0.05, 0.025), metavar="R1,R2",
                   help="noise targets of the dataset bench, one run each (default 0.05,0.025)")
    p.add_argument("--workers", type=int, default=1, help="the dataset bench's processes (default 1)")
    p.add_argument("--pbr-photons", type=int, default=1 << 20, help="bench pbr: photons per LED per pass")
    p.add_argument("--pbr-no-contact-runs", type=int, default=8, metavar="M", help="bench pbr: the no-contact "
                   "cache's runs per pass (0: off)")
    p.add_argument("--calibrate-cases", type=int, default=1, help="calibrate benchmark: virtual sensors (default 1)")
    p.add_argument("--calibrate-taps", type=int, default=2, help="calibrate benchmark: taps each (default 2)")
    p.add_argument("--physical", action="store_true", help="also the physical diagnosis (diagnose benchmark "
                   "--physical), last; off by default: one case renders 12 taps three times")
    p.add_argument("--physical-cases", type=int, default=1, help="with --physical: cases (default 1)")
    p.add_argument("--work", metavar="DIR", help="keep each bench's JSON, logs and cache here (default: a "
                   "temporary folder)")
    p.add_argument("--wheels", default=".whl", metavar="DIR", help="the wheel folder, whose manifest names the "
                   "commit where git cannot (default .whl)")
