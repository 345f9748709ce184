"""Every program a script compiles: its name, XLA compile seconds, lowering seconds and HLO size.

Each stage runs in a fresh Python process pinned to one core: the README example, its first
``jax.grad``, ``jl.fit`` and ``jl.simulate_batch`` (the stages of ``bench_first_result``), and every
cookbook page (``docs/cookbook/*.md``: the page's python blocks in order, in one namespace, in a
fresh working directory, matplotlib on Agg, as ``tests/test_readme.py`` runs them). The child
records, with ``jax.monitoring`` listeners, each XLA compilation (event
``/jax/core/compile/backend_compile_duration``, keyword ``fun_name``) and its lowering
(``/jax/core/compile/jaxpr_to_mlir_module_duration``), and dumps every compiled StableHLO module
(``jax_dump_ir_to``, without debug locations: the benchmark configures JAX, jaxlag never does).
JAX writes one ``jax_irNNNN_<module>_compile.mlir`` per compilation, just before compiling it; the
files new at each compile event are that program's. Per program the table gives the lines and
bytes of that module and its host callbacks (``custom_call`` targets containing ``callback``: JAX's
persistent compilation cache does not store a program with a host callback, so every process
compiles it again). With ``--sites`` a column gives the innermost frame in ``src/jaxlag/`` on the
stack at each compilation, jaxlag's jit wrapper left out (``script`` when jaxlag is not on the
stack: the script's own eager ``jax.numpy``, ``jax.jit``, or the transposes of ``jax.grad``). The
traces (event ``/jax/core/compile/jaxpr_trace_duration``, one per traced function, nested ones
included) are counted per stage, and the names traced more than once listed.

    python -m benchmarks.program_table                    # all stages, ~15 minutes on one core
    python -m benchmarks.program_table readme fit         # some stages
    python -m benchmarks.program_table --sites readme     # also: which jaxlag line compiled each
    python -m benchmarks.program_table --repeat 3 readme  # seconds: the minimum of 3 runs
    python -m benchmarks.program_table --baseline ../old --repeat 2 --json both.json
    python -m benchmarks.program_table --compare both.json readme fit   # its tables, readme and fit in full

``--root`` (default: this checkout) and ``--baseline`` point the child processes
(``PYTHONPATH=<root>/src``, working directory, cookbook pages) at a checkout, e.g. a worktree of an
older commit, while this script runs from here. With ``--baseline`` each stage (those present in
both checkouts) runs alternately on the baseline ("before") and on the root ("after"), so that a
change of the machine's load falls on both, and a before → after table ends the output.
Counts, HLO sizes and callbacks do not depend on the load; seconds do (the minimum of
``--repeat`` runs is kept).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import textwrap

from .bench_first_result import STAGES

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPT_STAGES = ("readme", "grad", "fit", "batch")
_FENCE = re.compile(r"^(\s*)```(\S*)\s*$")
_CALLBACK = re.compile(r"custom_call\s*@(\w*callback\w*)")

PRELUDE = textwrap.dedent('''
    import os, sys, json, time, traceback
    try:
        os.sched_setaffinity(0, {int(os.environ["BENCH_CORE"])})
    except (AttributeError, OSError, KeyError, ValueError):
        pass
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_dump_ir_to", os.environ["BENCH_DUMP"])
    jax.config.update("jax_include_debug_info_in_dumps", False)
    _dump = os.environ["BENCH_DUMP"]
    _seen = set()
    _programs, _lowered, _traces = [], {}, {}
    _step = [0]
    def _site():
        """Innermost frame in src/jaxlag/ (not jaxlag's jit wrapper) and the outermost, else None."""
        frames = [f for f in traceback.extract_stack() if "/src/jaxlag/" in f.filename.replace(os.sep, "/")
                  and not (f.filename.endswith("_compile.py")
                          and f.name in ("__call__", "lower"))]
        def fmt(f):
            path = f.filename.replace(os.sep, "/")
            return f"{path[path.index('/src/jaxlag/') + 1:]}:{f.lineno} {f.name}"
        return (fmt(frames[-1]), fmt(frames[0])) if frames else (None, None)
    def _listen(event, duration, **kwargs):
        name = kwargs.get("fun_name", "?")
        if event == "/jax/core/compile/jaxpr_trace_duration":
            n, s = _traces.get(name, (0, 0.0))
            _traces[name] = (n + 1, s + duration)
        elif event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            _lowered.setdefault(name, []).append(duration)
        elif event == "/jax/core/compile/backend_compile_duration":
            new = sorted(f for f in os.listdir(_dump) if f.endswith("_compile.mlir") and f not in _seen)
            _seen.update(new)
            lowerings = _lowered.get(name) or [None]
            inner, outer = _site()
            _programs.append({"name": name, "compile_s": duration, "lower_s": lowerings.pop(0),
                              "files": new, "step": None, "site": inner, "entry": outer})
    jax.monitoring.register_event_duration_secs_listener(_listen)
    import jax.numpy as jnp
    import numpy as np
    def step(name):
        """Name the step that just ended: the programs compiled since the previous call."""
        for program in _programs[_step[0]:]:
            program["step"] = name
        _step[0] = len(_programs)
''')

EPILOGUE = textwrap.dedent("""
    step("exit")
    with open(os.environ["BENCH_OUT"], "w") as _f:
        json.dump({"programs": _programs, "traces": _traces,
                   "lowered_not_compiled": {k: len(v) for k, v in _lowered.items() if v},
                   "versions": {"jax": jax.__version__,
                                "diffrax": __import__("diffrax").__version__}}, _f)
""")

PAGE = textwrap.dedent("""
    import matplotlib
    matplotlib.use("Agg")
    _page = os.environ["BENCH_PAGE"]
    with open(_page, encoding="utf-8") as _f:
        _source = _f.read()
    exec(compile(_source, _page, "exec"), {"__name__": "__main__"})
    step("page")
""")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(first_line, source)`` of each ```python block of a Markdown page (as tests/test_readme.py)."""
    blocks, language, start, body, indent = [], None, 0, [], ""
    for number, line in enumerate(text.splitlines(), start=1):
        fence = _FENCE.match(line)
        if language is None:
            if fence:
                indent, language, start, body = fence.group(1), fence.group(2), number + 1, []
        elif fence and not fence.group(2):
            if language == "python":
                blocks.append((start, "\n".join(body) + "\n"))
            language = None
        else:
            body.append(line[len(indent) :] if line.startswith(indent) else line)
    return blocks


def page_script(page: pathlib.Path) -> str:
    """A cookbook page's python blocks as one script, each block at its own line numbers."""
    lines: list[str] = []
    for first_line, source in python_blocks(page.read_text("utf-8")):
        lines += [""] * (first_line - 1 - len(lines)) + source.splitlines()
    return "\n".join(lines) + "\n"


def cookbook_pages(root: pathlib.Path) -> dict[str, pathlib.Path]:
    pages = sorted((root / "docs" / "cookbook").glob("*.md"))
    return {p.stem: p for p in pages if python_blocks(p.read_text("utf-8"))}


def _environment_lines(source: str) -> str:
    """The page's top-level ``os.environ[...] = ...`` lines: they must run before JAX is imported."""
    lines = [line for line in source.splitlines() if re.match(r"os\.environ\[.*\]\s*=", line)]
    return "import os\n" + "\n".join(lines) + "\n" if lines else ""


def _module_stats(path: pathlib.Path) -> dict:
    text = path.read_text("utf-8")
    body = re.sub(r"^module @\S+", "module", text, count=1, flags=re.M)
    return {
        "lines": text.count("\n"),
        "bytes": len(text.encode()),
        "callbacks": len(_CALLBACK.findall(text)),
        "hash": hashlib.sha1(body.encode()).hexdigest()[:12],
    }


def _core() -> int:
    try:
        return sorted(os.sched_getaffinity(0))[-1]
    except AttributeError:
        return 0


def run_stage(name: str, root: pathlib.Path, core: int) -> dict:
    """Run one stage in a fresh process with ``root``'s sources; its programs with their HLO sizes."""
    pages = cookbook_pages(root)
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = pathlib.Path(tmp)
        dump, out, work = tmp_path / "dump", tmp_path / "out.json", tmp_path / "work"
        dump.mkdir()
        work.mkdir()
        env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "XLA_FLAGS")}
        env.update(
            BENCH_DUMP=str(dump),
            BENCH_OUT=str(out),
            BENCH_CORE=str(core),
            BENCH_STAGE=name,
            MPLBACKEND="Agg",
            PYTHONPATH=os.pathsep.join([str(root / "src")] + [p for p in [env.get("PYTHONPATH")] if p]),
        )
        if name in pages:
            env["BENCH_PAGE"] = str(tmp_path / f"{name}.py")
            source = page_script(pages[name])
            pathlib.Path(env["BENCH_PAGE"]).write_text(source, "utf-8")
            code = _environment_lines(source) + PRELUDE + PAGE + EPILOGUE
            cwd = work
        else:
            code = PRELUDE + textwrap.dedent(STAGES[name]) + EPILOGUE
            cwd = root
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=cwd)
        if done.returncode != 0:
            raise RuntimeError(f"stage {name} failed:\n{done.stderr[-3000:]}")
        result = json.loads(out.read_text())
        for program in result["programs"]:
            stats = [_module_stats(dump / f) for f in program.pop("files")]
            program["lines"] = sum(s["lines"] for s in stats)
            program["bytes"] = sum(s["bytes"] for s in stats)
            program["callbacks"] = sum(s["callbacks"] for s in stats)
            program["hash"] = "+".join(s["hash"] for s in stats)
    result["root"] = str(root)
    return result


def _keep_fastest(result: dict, again: dict, name: str) -> None:
    """Each program's seconds: the minimum of two runs (on a busy machine the least disturbed)."""
    if not _same(result, again):
        raise RuntimeError(f"stage {name}: another run compiled other programs")
    for p, q in zip(result["programs"], again["programs"]):
        p["compile_s"] = min(p["compile_s"], q["compile_s"])
        p["lower_s"] = min(p["lower_s"] or 0.0, q["lower_s"] or 0.0)


def _same(a: dict, b: dict) -> bool:
    return [p["hash"] for p in a["programs"]] == [p["hash"] for p in b["programs"]]


def measure(name: str, roots: list[pathlib.Path], core: int, repeat: int) -> list[dict]:
    """``name`` on each checkout, alternating (A, B, A, B, ...) ``repeat`` times, so that a change
    of the machine's load falls on both; per checkout the fastest seconds of each program."""
    results: list[dict] = []
    for r in range(repeat):
        for i, root in enumerate(roots):
            result = run_stage(name, root, core)
            if r == 0:
                results.append(result)
            else:
                _keep_fastest(results[i], result, name)
    for result in results:
        result["repeat"] = repeat
    return results


def group(programs: list[dict]) -> list[dict]:
    """Programs with the same name together, in order of first compilation."""
    rows: dict[str, dict] = {}
    for p in programs:
        row = rows.setdefault(
            p["name"],
            {
                "name": p["name"],
                "n": 0,
                "compile_s": 0.0,
                "lower_s": 0.0,
                "lines": 0,
                "bytes": 0,
                "callbacks": 0,
                "with_callbacks": 0,
                "hashes": set(),
                "sites": [],
            },
        )
        row["n"] += 1
        row["compile_s"] += p["compile_s"]
        row["lower_s"] += p["lower_s"] or 0.0
        row["lines"] += p["lines"]
        row["bytes"] += p["bytes"]
        row["callbacks"] += p["callbacks"]
        row["with_callbacks"] += p["callbacks"] > 0
        row["hashes"].add(p["hash"])
        site = p.get("site") or "script"
        if site not in row["sites"]:
            row["sites"].append(site)
    return list(rows.values())


def totals(programs: list[dict]) -> dict:
    return {
        "programs": len(programs),
        "names": len({p["name"] for p in programs}),
        "compile_s": sum(p["compile_s"] for p in programs),
        "lower_s": sum(p["lower_s"] or 0.0 for p in programs),
        "lines": sum(p["lines"] for p in programs),
        "bytes": sum(p["bytes"] for p in programs),
        "with_callbacks": sum(p["callbacks"] > 0 for p in programs),
        "jaxlag": sum(p.get("site") is not None for p in programs),
    }


def _count(row: dict) -> str:
    n, distinct = row["n"], len(row["hashes"])
    return str(n) if distinct == n or n == 1 else f"{n} ({distinct} distinct)"


def print_stage(name: str, result: dict, sites: bool = False) -> None:
    programs = result["programs"]
    print(f"\n### {name}\n")
    header = "| program | n | compile s | lowering s | HLO lines | HLO KiB | callbacks |"
    print(header + (" called from (jaxlag) |" if sites else ""))
    print("|---" * (7 + sites) + "|")
    for row in group(programs):
        cb = "–" if not row["callbacks"] else f"{row['callbacks']} in {row['with_callbacks']}"
        line = (
            f"| `{row['name']}` | {_count(row)} | {row['compile_s']:.2f} | {row['lower_s']:.2f} "
            f"| {row['lines']} | {row['bytes'] / 1024:.1f} | {cb} |"
        )
        print(line + (f" {'<br>'.join(row['sites'])} |" if sites else ""))
    t = totals(programs)
    print(
        f"\n**{name}**: {t['programs']} programs ({t['names']} names, {t['jaxlag']} compiled from inside "
        f"jaxlag), {t['compile_s']:.2f} s XLA compile, {t['lower_s']:.2f} s lowering, {t['lines']} HLO "
        f"lines ({t['bytes'] / 1024:.0f} KiB), {t['with_callbacks']} with host callbacks"
    )
    traced = result["traces"].values()
    print(f"traces: {sum(n for n, _ in traced)} ({sum(s for _, s in traced):.2f} s)")
    again = {k: v for k, v in result["traces"].items() if v[0] > 1}
    if again:
        print(
            "traced more than once: "
            + ", ".join(f"`{k}` ×{n}" for k, (n, _) in sorted(again.items(), key=lambda kv: -kv[1][0]))
        )
    if result.get("lowered_not_compiled"):
        print(f"lowered, not compiled: {result['lowered_not_compiled']}")


def _arrow(b, a, fmt: str = "{}") -> str:
    b, a = ("–" if x is None else fmt.format(x) for x in (b, a))
    return a if a == b else f"{b} → {a}"


def compare(before: dict, after: dict, detail: tuple[str, ...] = ("readme",)) -> None:
    """Before → after totals of the stages present in both, and per program for ``detail``."""
    print(
        "| stage | programs | compiled from jaxlag | XLA compile s | HLO lines | with host callbacks "
        "| traces | tracing s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in [n for n in after if n in before]:
        b, a = totals(before[name]["programs"]), totals(after[name]["programs"])
        tb, ta = (list(r[name]["traces"].values()) for r in (before, after))
        print(
            f"| {name} | {_arrow(b['programs'], a['programs'])} | {_arrow(b['jaxlag'], a['jaxlag'])} "
            f"| {b['compile_s']:.1f} → {a['compile_s']:.1f} | {_arrow(b['lines'], a['lines'])} "
            f"| {_arrow(b['with_callbacks'], a['with_callbacks'])} "
            f"| {_arrow(sum(n for n, _ in tb), sum(n for n, _ in ta))} "
            f"| {sum(s for _, s in tb):.2f} → {sum(s for _, s in ta):.2f} |"
        )
    for name in [n for n in detail if n in before and n in after]:
        rows_b = {r["name"]: r for r in group(before[name]["programs"])}
        rows_a = {r["name"]: r for r in group(after[name]["programs"])}
        print(f"\n### {name}: before → after\n")
        print("| program | n | XLA compile s | lowering s | HLO lines | host callbacks |")
        print("|---|---|---|---|---|---|")
        for key in [*rows_b, *(k for k in rows_a if k not in rows_b)]:
            b, a = rows_b.get(key, {}), rows_a.get(key, {})
            print(
                f"| `{key}` | {_arrow(b.get('n'), a.get('n'))} "
                f"| {_arrow(b.get('compile_s'), a.get('compile_s'), '{:.2f}')} "
                f"| {_arrow(b.get('lower_s'), a.get('lower_s'), '{:.2f}')} "
                f"| {_arrow(b.get('lines'), a.get('lines'))} "
                f"| {_arrow(b.get('callbacks'), a.get('callbacks'))} |"
            )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "stages",
        nargs="*",
        help=f"{', '.join(STAGES)} or a cookbook page (default: {', '.join(SCRIPT_STAGES)} and every page)",
    )
    parser.add_argument("--root", type=pathlib.Path, default=ROOT, help="checkout to measure (src/, docs/)")
    parser.add_argument("--baseline", type=pathlib.Path, help="a second checkout, measured alternately")
    parser.add_argument("--json", type=pathlib.Path, help="results file; runs accumulate in it")
    parser.add_argument("--core", type=int, default=_core(), help="core to pin the children to")
    parser.add_argument("--repeat", type=int, default=1, help="runs per stage; seconds: the minimum")
    parser.add_argument("--sites", action="store_true", help="a column with the jaxlag line of each compile")
    parser.add_argument(
        "--compare",
        action="append",
        type=pathlib.Path,
        metavar="JSON",
        help="before → after tables of a --baseline results file (or of two: --compare A --compare B)",
    )
    args = parser.parse_args(argv)
    if args.compare:
        loaded = [json.loads(p.read_text()) for p in args.compare]
        before, after = (loaded[0]["before"], loaded[0]["after"]) if len(loaded) == 1 else loaded
        compare(before, after, tuple(args.stages) or ("readme",))
        return
    roots = [args.root.resolve()] if args.baseline is None else [args.baseline.resolve(), args.root.resolve()]
    labels = ["after"] if args.baseline is None else ["before", "after"]
    in_all = set.intersection(*(set(STAGES) | set(cookbook_pages(root)) for root in roots))
    names = args.stages or [n for n in [*SCRIPT_STAGES, *cookbook_pages(roots[-1])] if n in in_all]
    unknown = [n for n in names if n not in in_all]
    if unknown:
        parser.error(f"unknown stage(s) {unknown}; choose from {sorted(in_all)}")
    # Stages already in the JSON file are kept; a stage measured again keeps the fastest seconds
    # of all its runs (when it compiled the same programs), so that runs accumulate in one file.
    # With --baseline: {"before": {stage: ...}, "after": {stage: ...}}.
    saved = json.loads(args.json.read_text()) if args.json and args.json.exists() else {}
    results = {label: saved.get(label, {}) for label in labels} if args.baseline else {"after": saved}
    for name in names:
        for label, result in zip(labels, measure(name, roots, args.core, args.repeat)):
            kept = results[label].get(name)
            if kept is not None and kept["root"] == result["root"] and _same(kept, result):
                _keep_fastest(result, kept, name)  # measured again: the fastest seconds of all runs
                result["repeat"] += kept.get("repeat", 1)
            results[label][name] = result
            if name == names[0]:
                v = result["versions"]
                print(f"{label}: {result['root']}; jax {v['jax']}, diffrax {v['diffrax']}, CPU, one core")
            print_stage(name if args.baseline is None else f"{name}, {label}", result, args.sites)
        sys.stdout.flush()
        if args.json:
            args.json.write_text(json.dumps(results if args.baseline else results["after"], indent=1))
    if args.baseline is not None:
        print()
        compare(results["before"], results["after"], tuple(n for n in ("readme",) if n in names))


if __name__ == "__main__":
    main(sys.argv[1:])
