"""`make test` wall time: the recipe of one commit against another's, in one run.

Each run clones the repository into a scratch directory, checks out its commit (a clean
clone: no feature or numba caches, no build/), asks that commit's Makefile for the commands
of its ``test`` target (``make -n``, with ``PY`` pointing at the given venv and the venv's
install stamp taken as up to date, so nothing is installed) and runs them there with
``PYTHONPATH`` set to the clone. The runs are measured one after another in the same
invocation, so the ratio between them is the figure to read when the machine is shared;
the load average is recorded before and after each command, and the CPU time of the
command's processes (user + system, children included) beside the wall time.

    python benchmarks/make_test.py                      # serial=HEAD:0, then parallel=HEAD:2
    python benchmarks/make_test.py --run after=HEAD:2 --run before=COMMIT
    python benchmarks/make_test.py --quick              # HEAD's recipe on one small test file -> results/quick/

``LABEL=REV[:WORKERS]``: WORKERS is passed as ``TEST_WORKERS`` to the Makefile (commits
whose Makefile has no such variable run their recipe as written). The JSON is rewritten
after every command, so an interrupted invocation keeps what it measured.
"""
from __future__ import annotations

import argparse
import os
import re
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import ROOT, result_path, write_result

#: what ``--quick`` runs in place of the recipe's test paths (one small, fast test file)
QUICK_TESTS = ("tests/base/test_settings.py",)

SUMMARY = re.compile(r"^=*\s*(?P<body>(\d+ \w+(, )?)+) in (?P<secs>[\d.]+)s", re.MULTILINE)


def parse_run(spec: str) -> dict:
    """``LABEL=REV[:WORKERS]`` -> {"label", "rev", "workers"}."""
    m = re.fullmatch(r"(?P<label>[\w.-]+)=(?P<rev>[^:\s]+)(:(?P<workers>\d+))?", spec)
    if m is None:
        raise argparse.ArgumentTypeError(f"--run {spec!r}: expected LABEL=REV[:WORKERS], e.g. after=HEAD:2")
    w = m.group("workers")
    return {"label": m.group("label"), "rev": m.group("rev"), "workers": None if w is None else int(w)}


def git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def test_commands(tree: Path, venv: Path, workers: int | None) -> list[str]:
    """The shell commands of ``make test`` in ``tree`` (its own Makefile), run with ``venv``."""
    stamp = venv / ".installed-stamp"
    argv = ["make", "-s", "-n", "-C", str(tree), "-o", str(stamp), "test", f"VENV={venv}",
            f"PY={venv / 'bin' / 'python'}"]
    if workers is not None:
        argv.append(f"TEST_WORKERS={workers}")
    out = subprocess.run(argv, check=True, capture_output=True, text=True).stdout
    cmds = [ln.split("#", 1)[0].strip() for ln in out.splitlines() if ln.strip()]
    bad = [c for c in cmds if "pytest" not in c]
    if bad:
        raise SystemExit(f"{tree}/Makefile: `make -n test` would run more than pytest: {bad}")
    return cmds


def counts(text: str) -> dict:
    """pytest's final summary ("836 passed, 3 skipped in 940.12s") as numbers."""
    found = SUMMARY.findall(text)
    if not found:
        return {}
    body = found[-1][0]
    return {k: int(n) for n, k in re.findall(r"(\d+) (\w+)", body)}


def with_tests(cmd: str, tests: list[str]) -> str:
    """``cmd`` with its test paths (``notebooks``, ``tests``) replaced by ``tests``."""
    argv = shlex.split(cmd)
    keep = [a for a in argv if a not in ("notebooks", "tests")]
    return shlex.join(keep + list(tests))


def run_command(cmd: str, cwd: Path, env: dict, log: Path) -> dict:
    argv = shlex.split(cmd)
    env = dict(env)
    while argv and re.fullmatch(r"[A-Za-z_]\w*=.*", argv[0]):   # the recipe's VAR=value prefix
        k, _, v = argv.pop(0).partition("=")
        env[k] = v
    load_before = os.getloadavg()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = proc.stdout + proc.stderr
    log.write_text(out, encoding="utf-8")
    return {
        "command": cmd.replace(str(env["BT_VENV"]), "VENV"),
        "returncode": proc.returncode,
        "wall_s": round(wall, 1),
        "cpu_s": round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 1),
        "counts": counts(out),
        "failed": [ln for ln in out.splitlines() if ln.startswith(("FAILED", "ERROR"))][:50],
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=parse_run, action="append",
                    help="LABEL=REV[:WORKERS], measured in the order given (repeatable; default: "
                         "serial=HEAD:0 then parallel=HEAD:2)")
    ap.add_argument("--venv", type=Path, default=ROOT / ".venv",
                    help="the venv whose python runs the tests (default .venv)")
    ap.add_argument("--out", type=Path, default=None, help="default benchmarks/results/make_test.json (--quick: results/quick/)")
    ap.add_argument("--tests", nargs="+", default=None, help="run these test paths in place of the recipe's")
    ap.add_argument("--quick", action="store_true", help=f"one run of HEAD's recipe (1 worker) on {', '.join(QUICK_TESTS)}")
    ap.add_argument("--only", choices=("tests", "notebooks"),
                    help="run only the recipe's commands that name this directory among their "
                         "arguments (a recipe that runs tests/ and notebooks/ in one command runs "
                         "that command either way)")
    ap.add_argument("--keep", action="store_true", help="keep the clones (the pytest output is always kept)")
    args = ap.parse_args(argv)
    args.out = result_path("make_test", args.quick, args.out)
    if args.quick:
        args.run, args.tests = args.run or [parse_run("quick=HEAD:0")], args.tests or list(QUICK_TESTS)
    args.run = args.run or [parse_run("serial=HEAD:0"), parse_run("parallel=HEAD:2")]
    venv = args.venv.absolute()
    if not (venv / "bin" / "python").exists():
        raise SystemExit(f"--venv {venv}: no bin/python there")
    scratch = Path(tempfile.mkdtemp(prefix="bt-make-test-"))
    result = {"tests": args.tests or "the recipe's", "machine": {"niceness": os.nice(0)}, "runs": []}
    for run in args.run:
        sha = git("rev-parse", "--verify", run["rev"] + "^{commit}")
        tree = scratch / run["label"]
        git("clone", "-q", "--no-checkout", str(ROOT), str(tree))
        git("checkout", "-q", "--detach", sha, cwd=tree)
        env = {**os.environ, "PYTHONPATH": str(tree), "BT_VENV": str(venv)}
        entry = {**run, "commit": sha, "subject": git("log", "-1", "--format=%s", sha), "commands": []}
        result["runs"].append(entry)
        cmds = [c for c in test_commands(tree, venv, run["workers"])
                if args.only is None or args.only in shlex.split(c)]
        if args.tests:
            cmds = [with_tests(c, args.tests) for c in cmds]
        for i, cmd in enumerate(cmds):
            print(f"[{run['label']}] {cmd}", flush=True)
            log = scratch / f"{run['label']}-{i}.log"
            rec = run_command(cmd, tree, env, log)
            entry["commands"].append(rec)
            print(f"  -> rc {rec['returncode']}, {rec['wall_s']} s wall, {rec['cpu_s']} s CPU, {rec['counts']}, "
                  f"load {rec['load_before'][0]} -> {rec['load_after'][0]}; output: {log}", flush=True)
            entry["wall_s"] = round(sum(c["wall_s"] for c in entry["commands"]), 1)
            entry["cpu_s"] = round(sum(c["cpu_s"] for c in entry["commands"]), 1)
            entry["passed"] = sum(c["counts"].get("passed", 0) for c in entry["commands"])
            entry["ok"] = all(c["returncode"] == 0 for c in entry["commands"])
            first = result["runs"][0]
            result["wall_ratio_to_first"] = {r["label"]: round(r["wall_s"] / first["wall_s"], 3)
                                             for r in result["runs"] if first.get("wall_s")}
            write_result(args.out, result)
        if not args.keep:
            shutil.rmtree(tree, ignore_errors=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
