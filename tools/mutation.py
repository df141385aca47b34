"""Mutation testing of the pure core with mutmut, on demand (not in CI): docs/mutation_testing.md.

    pip install mutmut==3.8.1                  # once, into the project's venv
    python tools/mutation.py run               # ~50 min on one core; mutants/ holds the results
    python tools/mutation.py report            # counts, kill rate, the survivors left to judge
    python tools/mutation.py run "safeil_sumo.planners.idm.*"   # re-run a part (fnmatch on mutant names)
    python tools/mutation.py run --safety --workers 2  # the safety-critical modules
    python tools/mutation.py judge NAME... --why "..."  # survivors judged equivalent
    python tools/mutation.py record            # the safety modules' kill rates and code digests

mutmut reads its settings (files to mutate, the fast unit tests to run) from ``setup.cfg``; this
script adds the function scope (SCOPE below: whole files, and the named functions of the larger
experiment modules) and one worker process (the machine's cores are shared).

``tools/mutation_equivalent.tsv`` lists the surviving mutants judged EQUIVALENT (the program's
behaviour cannot change), one per line: ``mutant name <TAB> function hash <TAB> reason``. The
hash is mutmut's hash of the function when it was judged: once the function changes, the entry
is reported stale and must be judged again (mutant numbers shift with the code).
"""

from __future__ import annotations

import argparse
import ast
import csv
import datetime
import fnmatch
import hashlib
import importlib.metadata
import io
import json
import subprocess
import sys
import tokenize
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EQUIVALENT = ROOT / "tools" / "mutation_equivalent.tsv"
# the last run's kill rate and code digest per safety-critical module (tests/test_mutation_record.py
# fails once a module's code no longer matches: rerun its mutants, then `record`)
RECORD = ROOT / "tools" / "mutation_record.json"
# the safety-critical modules (issue 43), whole files: the certification bounds, branch and bound
# and the certificate, the brake guard, falsification, the gap probe, the leader-response suite
# and the safety filter, the monitors
SAFETY_MODULES = (
    "safeil_sumo.learn.bounds", "safeil_sumo.learn.certify_margins",
    "safeil_sumo.learn.branch_and_bound",
    "safeil_sumo.learn.certificate", "safeil_sumo.sim.brake_guard", "safeil_sumo.sim.monitors",
    "safeil_sumo.experiments.falsification_search", "safeil_sumo.experiments.gap_step_responses",
    "safeil_sumo.experiments.suite", "safeil_sumo.planners.safety_filter",
    # the closed-loop reachability of the ARCH-COMP ACC benchmark (issue 41)
    "safeil_sumo.learn.reach",
    # the closed loop's one-period bound, the barrier check and its certificate file (issue 41)
    "safeil_sumo.learn.loop_invariant", "safeil_sumo.learn.loop_barrier",
    "safeil_sumo.learn.closed_loop_certificate",
)
SAFETY_SCOPE = (
    "safeil_sumo.learn.bounds.*",
    "safeil_sumo.learn.certify_margins.*",
    "safeil_sumo.learn.branch_and_bound.*",
    "safeil_sumo.learn.certificate.*",
    "safeil_sumo.sim.brake_guard.*",
    "safeil_sumo.experiments.falsification_search.*",
    # the gap probe but its figure (plot, the series it draws) and the reader of the real data
    *(f"safeil_sumo.experiments.gap_step_responses.x_{name}__mutmut_*" for name in (
        "initial_gap_m", "probe_scenario", "probe_task", "kind_of", "step_time_s", "leader_distance_m",
        "check_fits", "time_gap", "window_mean", "settling_time", "_first_crossing",
        "rise_time", "overshoot", "drift", "response_metrics", "probe_extras", "run_step",
        "probe_tasks", "steady_following", "human_time_gap_bands", "table")),
    "safeil_sumo.experiments.suite.*",
    "safeil_sumo.planners.safety_filter.*",
    "safeil_sumo.sim.monitors.*",
    "safeil_sumo.learn.reach.*",
    "safeil_sumo.learn.loop_invariant.*",
    "safeil_sumo.learn.loop_barrier.*",
    "safeil_sumo.learn.closed_loop_certificate.*",
)
# the certification modules' tests are the slowest (branch and bound runs): their kill rate is
# measured on a seeded uniform sample of their mutants (each name in or out by its hash)
SAMPLE_FRACTION = {"safeil_sumo.learn.bounds": 0.25, "safeil_sumo.learn.branch_and_bound": 0.25,
                   "safeil_sumo.learn.certify_margins": 0.25, "safeil_sumo.learn.reach": 0.25,
                   "safeil_sumo.learn.loop_invariant": 0.25, "safeil_sumo.learn.loop_barrier": 0.25,
                   "safeil_sumo.learn.closed_loop_certificate": 0.25}
# fnmatch patterns over mutmut's mutant names (module.x_function__mutmut_N,
# module.xǁClassǁmethod__mutmut_N); the files themselves are listed in setup.cfg
SCOPE = (
    "safeil_sumo.core.geometry.*",
    "safeil_sumo.core.bspline.*",
    "safeil_sumo.planners.idm.*",
    "safeil_sumo.learn.losses.*",
    "safeil_sumo.learn.envelope.*",
    "safeil_sumo.sim.monitors.*",
    # the replay statistics
    "safeil_sumo.experiments.window_replays.x_bootstrap_ci__mutmut_*",
    "safeil_sumo.experiments.window_replays.x_aggregate__mutmut_*",
    "safeil_sumo.experiments.window_replays.x_literature_summary__mutmut_*",
    "safeil_sumo.experiments.window_replays.x__column__mutmut_*",
    "safeil_sumo.experiments.window_replays.x__nan_stat__mutmut_*",
    "safeil_sumo.experiments.window_replays.x__headway_hist__mutmut_*",
    # the recorded leader's speed and its drift filter
    "safeil_sumo.roads.recorded_road.x_drift_corrected_speed__mutmut_*",
    "safeil_sumo.roads.recorded_road.x_leader_speed__mutmut_*",
    "safeil_sumo.roads.recorded_road.x_recorded_leader_travel__mutmut_*",
) + SAFETY_SCOPE

# mutmut's exit codes per mutant (mutmut/__main__.py: status_by_exit_code)
KILLED = {1, 3}  # a test failed (3: pytest's internal error)
TIMEOUT = {-24, 24, 36, 152, 255}  # CPU or time limit: counted as caught (an endless loop)
SURVIVED = {0}  # the tests passed
NO_TESTS = {5, 33}  # no selected test executes the function: counted as survived


def function_of(mutant: str) -> str:
    """``safeil_sumo.planners.idm.x_fit_idm__mutmut_3`` -> ``safeil_sumo.planners.idm.x_fit_idm``."""
    return mutant.rsplit("__mutmut_", 1)[0]


def in_sample(name: str) -> bool:
    """Whether mutant ``name`` is in its module's sample (:data:`SAMPLE_FRACTION`; all if the
    module is not sampled): the first 8 bytes of its name's sha256 as a uniform draw."""
    fraction = SAMPLE_FRACTION.get(name.rsplit(".", 1)[0], 1.0)
    draw = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") / 2.0 ** 64
    return draw < fraction


def load_results(patterns: tuple[str, ...]) -> tuple[dict[str, int | None], dict[str, str]]:
    """Exit code per mutant in scope and sample (None: not run yet) and mutmut's hash per
    function."""
    codes: dict[str, int | None] = {}
    hashes: dict[str, str] = {}
    for meta in sorted((ROOT / "mutants").rglob("*.py.meta")):
        data = json.loads(meta.read_text())
        module = ".".join(meta.relative_to(ROOT / "mutants").with_suffix("").with_suffix("").parts)
        for name, digest in data.get("hash_by_function_name", {}).items():
            hashes[f"{module}.{name}"] = digest
        for name, code in data["exit_code_by_key"].items():
            if any(fnmatch.fnmatchcase(name, p) for p in patterns) and in_sample(name):
                codes[name] = code
    return codes, hashes


def load_equivalent() -> dict[str, tuple[str, str]]:
    """Mutant name -> (function hash, reason) from the equivalents file."""
    if not EQUIVALENT.is_file():
        return {}
    rows = csv.reader(EQUIVALENT.read_text().splitlines(), delimiter="\t")
    out = {}
    for k, row in enumerate(rows, 1):
        if not row or row[0].startswith("#"):
            continue
        if len(row) != 3:
            sys.exit(f"{EQUIVALENT}:{k}: expected 3 tab-separated fields, got {len(row)}")
        out[row[0]] = (row[1], row[2])
    return out


def classify(patterns: tuple[str, ...]) -> tuple[dict[str, Counter], list[str], list[str]]:
    """Per module, how many mutants in scope were killed, timed out, judged equivalent, survived,
    had no test or were not run; the survivors to judge; the stale equivalents."""
    codes, hashes = load_results(patterns)
    equivalent = load_equivalent()
    stale = sorted(m for m, (h, _) in equivalent.items()
                   if m in codes and hashes.get(function_of(m)) != h)
    per_module: dict[str, Counter] = {}
    left = []
    for name, code in sorted(codes.items()):
        if code is None:
            kind = "not run"
        elif code in KILLED:
            kind = "killed"
        elif code in TIMEOUT:
            kind = "timeout"
        elif code in NO_TESTS:
            kind = "no tests"
        elif code in SURVIVED:
            kind = "equivalent" if name in equivalent and name not in stale else "survived"
        else:
            kind = f"other ({code})"
        per_module.setdefault(name.rsplit(".", 1)[0], Counter())[kind] += 1
        if kind in ("survived", "no tests"):
            left.append(name)
    return per_module, left, stale


def kill_rate(c: Counter) -> tuple[int, int]:
    """(caught, non-equivalent mutants that ran): timeouts count as caught."""
    caught = c["killed"] + c["timeout"]
    return caught, sum(c.values()) - c["equivalent"] - c["not run"]


def report(patterns: tuple[str, ...]) -> int:
    per_module, left, stale = classify(patterns)
    if not per_module:
        print("no mutants in scope: run `python tools/mutation.py run` first", file=sys.stderr)
        return 2
    cols = ("killed", "timeout", "equivalent", "survived", "no tests", "not run")
    print(f"{'module':44s} " + " ".join(f"{c:>10s}" for c in cols) + "  kill rate")
    kinds: Counter = Counter()
    for module, c in per_module.items():
        caught, candidates = kill_rate(c)
        rate = f"{100 * caught / candidates:9.1f} %" if candidates else ""
        print(f"{module:44s} " + " ".join(f"{c[k]:10d}" for k in cols) + rate)
        kinds.update(c)
    caught, candidates = kill_rate(kinds)
    print(f"\nmutants {sum(kinds.values())}: killed {kinds['killed']}, timeout "
          f"{kinds['timeout']}, equivalent {kinds['equivalent']}, survived {kinds['survived']}, "
          f"no tests {kinds['no tests']}, not run {kinds['not run']}")
    others = {k: v for k, v in kinds.items() if k.startswith("other")}
    if others:
        print(f"other exit codes: {others}")
    if candidates:
        print(f"kill rate of non-equivalent mutants: {caught}/{candidates} = "
              f"{100 * caught / candidates:.1f} %")
    for name in stale:
        print(f"stale equivalent (its function changed; judge again): {name}")
    # judged mutants of this report's patterns that no longer exist (renumbered or removed)
    codes, _ = load_results(patterns)
    gone = sorted(m for m in set(load_equivalent()) - set(codes)
                  if any(fnmatch.fnmatch(m, p) for p in patterns) and in_sample(m))
    for name in gone:
        print(f"equivalent entry names no mutant in scope: {name}")
    if left:
        print(f"\n{len(left)} survivors to judge (`mutmut show NAME` prints the diff):")
        print("\n".join(left))
    return 0


def source_digest(path: Path) -> str:
    """sha256 of a module's code: its lines without comments, blank lines, docstrings and
    import statements, so that a change of documentation, or a module moved to another folder
    (mutmut never mutates an import: its mutants are the same), needs no new mutation run and
    any other change of code does (by lines, not tokens: Python 3.12 tokenizes f-strings
    differently)."""
    text = path.read_text()
    lines = text.splitlines()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for k in range(node.lineno - 1, node.end_lineno or node.lineno):
                lines[k] = ""
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            for k in range(body[0].lineno - 1, body[0].end_lineno or body[0].lineno):
                lines[k] = ""
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            row, col = tok.start
            lines[row - 1] = lines[row - 1][:col]
    code = "\n".join(line.rstrip() for line in lines if line.strip())
    return hashlib.sha256(code.encode()).hexdigest()


def module_path(module: str) -> Path:
    """``safeil_sumo.sim.brake_guard`` -> the file's path from the project root."""
    return Path(*module.split(".")).with_suffix(".py")


def record() -> int:
    """Write RECORD: per safety-critical module, its counts, kill rate (over the mutants that
    ran) and code digest, as measured by the last run; a module none of whose mutants ran
    keeps its last record while its code still matches that record's digest. Refused while a
    module has neither, or an equivalent is stale. Mutants not run are recorded as such."""
    per_module, _, stale = classify(SAFETY_SCOPE)
    old = json.loads(RECORD.read_text()) if RECORD.is_file() else {"modules": {}}
    previous = {path: {**entry, "measured": entry.get("measured", old.get("measured"))}
                for path, entry in old["modules"].items()}
    modules, missing = {}, []
    for module in SAFETY_MODULES:
        path = module_path(module)
        c = per_module.get(module)
        if c is None or c["not run"] == sum(c.values()):
            kept = previous.get(str(path))
            if kept is None or kept["source_digest"] != source_digest(ROOT / path):
                missing.append(module)
            else:
                modules[str(path)] = kept
            continue
        caught, candidates = kill_rate(c)
        modules[str(path)] = {
            "source_digest": source_digest(ROOT / path),
            "sample_fraction": SAMPLE_FRACTION.get(module, 1.0),
            **{k: c[k] for k in ("killed", "timeout", "equivalent", "survived", "no tests",
                                 "not run")},
            "kill_rate": round(caught / candidates, 4),
            "measured": datetime.date.today().isoformat()}
    if missing or stale:
        print(f"not recorded: run these safety modules first (missing {missing}, stale "
              f"equivalents {stale})", file=sys.stderr)
        return 2
    data = {"mutmut": importlib.metadata.version("mutmut"), "modules": modules}
    RECORD.write_text(json.dumps(data, indent=1) + "\n")
    print(f"wrote {RECORD.relative_to(ROOT)}")
    return 0


def judge(names: list[str], reason: str) -> int:
    """Add ``names`` (mutants that survived) to the equivalents file with their function's
    current hash and ``reason``."""
    codes, hashes = load_results(tuple(names))
    known = load_equivalent()
    rows = []
    for name in names:
        if codes.get(name) not in SURVIVED:
            print(f"{name}: not a survivor of the last run", file=sys.stderr)
            return 2
        if name not in known:
            rows.append(f"{name}\t{hashes[function_of(name)]}\t{reason}\n")
    with EQUIVALENT.open("a") as f:
        f.writelines(rows)
    print(f"{len(rows)} judged equivalent")
    return 0


def mutmut_fastest_tests_first(args: list[str]) -> int:
    """``mutmut <args>``, each mutant's tests run fastest first (mutmut hands them over in a
    set's order and stops at the first failure): a killed mutant costs its fastest failing
    test, not whichever test came first (the certification tests take 0.01-5 s each); of a
    sampled module only its sample is run."""
    import mutmut.__main__ as mutmut_main
    from mutmut.state import state
    from mutmut.workers import isolation

    collect = mutmut_main.collect_source_file_mutation_data

    def collect_in_sample(*, mutant_names):
        """Only the mutants in their module's sample (SAMPLE_FRACTION) are run."""
        mutants, by_path = collect(mutant_names=mutant_names)
        return [m for m in mutants if in_sample(m[1])], by_path
    mutmut_main.collect_source_file_mutation_data = collect_in_sample

    for runner in (isolation.ForkServerRunner, isolation.ForkRunner):
        def submit(self, name, tests, cpu_limit, estimated, _submit=runner.submit):
            durations = state().duration_by_test
            return _submit(self, name, sorted(tests, key=lambda t: (durations.get(t, 0.0), t)),
                           cpu_limit, estimated)
        runner.submit = submit
    try:
        mutmut_main.cli.main(args, prog_name="mutmut", standalone_mode=False)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("run", "report", "record", "judge"))
    ap.add_argument("patterns", nargs="*", help="fnmatch patterns of mutant names (default: "
                    "the whole scope)")
    ap.add_argument("--workers", type=int, default=1, help="mutants run at once (default 1: "
                    "the machine's cores are shared)")
    ap.add_argument("--safety", action="store_true", help="only the safety-critical modules")
    ap.add_argument("--why", help="judge: why the named survivors are equivalent")
    args = ap.parse_intermixed_args(argv)
    patterns = tuple(args.patterns) or (SAFETY_SCOPE if args.safety else SCOPE)
    if args.command == "record":
        return record()
    if args.command == "judge":
        if not args.patterns or not args.why:
            ap.error("judge takes mutant names and --why")
        return judge(args.patterns, args.why)
    if args.command == "run":
        cmd = [sys.executable, str(Path(__file__)), "mutmut", "run", "--max-children",
               str(args.workers), *patterns]
        # mutmut runs the tests in mutants/, one level deeper than the checkout: the tests that
        # read ../shared/data find it through a link beside the checkout's files (git-ignored)
        link = ROOT / "shared"
        made = not link.exists() and (ROOT.parent / "shared").is_dir()
        if made:
            link.symlink_to(ROOT.parent / "shared")
        try:
            code = subprocess.call(cmd, cwd=ROOT)
        finally:
            if made:
                link.unlink()
        if code:
            return code
    return report(patterns)


if __name__ == "__main__":
    if sys.argv[1:2] == ["mutmut"]:  # the run's own process (see mutmut_fastest_tests_first)
        sys.exit(mutmut_fastest_tests_first(sys.argv[2:]))
    sys.exit(main())
