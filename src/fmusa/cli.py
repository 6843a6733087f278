"""The ``fmusa`` command line.

Each subcommand is a function ``cmd_<name>(args) -> int`` registered in :func:`build_parser`;
new subcommands (sweep, inspect, diagnose, …) add a ``_add_<name>`` function there.

Every ``cmd_`` function imports what it needs when it runs, and this module's top imports only the
standard library and :mod:`fmusa.errors`, so ``fmusa --help`` and ``fmusa inspect`` answer quickly (no
pandas, scipy or matplotlib). A :class:`~fmusa.errors.FmusaError` (a mistake in the input: study file,
FMU, data, option) is printed as one line ``fmusa <command>: message``; anything else is a bug and
keeps its traceback.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from fmusa import __version__
from fmusa.errors import FmusaError, UsageError
from fmusa.fmi.info import SUPPORTED_FMI_VERSIONS

#: Table 2 of the paper: thresholds of the parameter search.
EPS_Y = 5e-4        # m, max |y|
EPS_V = 5e-5        # m/s, max |v_y|


def _parse_sets(items: list[str] | None) -> list[tuple[str, str]]:
    out = []
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise SystemExit(f"fmusa: --set expects NAME=VALUE, got {item!r}")
        out.append((name.strip(), value.strip()))
    return out


def _fmt(x: float) -> str:
    return f"{x:.6g}"


def _int_at_least(low: int):
    """An argparse ``type``: an integer >= ``low`` (argparse reports anything else as a usage error)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value
    return parse


def _delimiter(text: str) -> str:
    """--delimiter: one of the CSV delimiters, ``tab`` (or ``\\t``) for a tab."""
    from fmusa.diagnose.measured import DELIMITERS
    value = {"tab": "\t", "\\t": "\t"}.get(text.lower(), text)
    if value not in DELIMITERS:
        raise argparse.ArgumentTypeError(f"{text!r} is not a delimiter fmusa reads; use one of , ; | tab")
    return value


def _positive_float(text: str) -> float:
    """An argparse ``type``: a positive finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


# ---------------------------------------------------------------------------- pullout
def _add_pullout(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "pullout", help="simulate the paper's 411 N pullout and write a CSV and a figure",
        description="Force-driven pullout of the ScrewVertebra FMU: F_pull ramps linearly from 0 to "
                    "F_max (411 N) over t_ramp (10 s), then holds. Writes DIR/pullout.csv (SI units) "
                    "and DIR/pullout.png.")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", dest="sets",
                   help="override an FMU parameter (repeatable), e.g. --set c_y=1e6 --set d_y=500")
    p.add_argument("--stop-time", type=_positive_float, default=12.0, help="simulation end in s (default 12)")
    p.add_argument("--step", type=_positive_float, default=0.01, help="communication step in s (default 0.01)")
    p.add_argument("--fmu", type=Path, default=None,
                   help="with CSV files: an FMU of a model fmusa has a description of (ScrewVertebra; default "
                        "dist/ScrewVertebra.fmu); for any other FMU write a diagnosis study file")
    p.set_defaults(func=cmd_pullout)


def cmd_pullout(args: argparse.Namespace) -> int:
    from fmusa.applications.paper.scenario import PULLOUT_OUTPUTS, pullout
    from fmusa.fmi.runner import FMURunner

    with FMURunner(args.fmu) as fmu:
        params = {name: fmu.parse_value(name, value) for name, value in _parse_sets(args.sets)}  # FMUError
        effective = {**fmu.start_values(), **params}
        df = pullout(params, stop_time=args.stop_time, step=args.step, runner=fmu)
    df = df[["time", *PULLOUT_OUTPUTS]]
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "pullout.csv"
    png_path = out / "pullout.png"
    from fmusa.files import atomic_path

    with atomic_path(csv_path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10g", encoding="utf-8")
    plot_pullout(df, effective, png_path)
    last = df.iloc[-1]
    print(f"{_load_case(effective)}: c_y = {_fmt(effective['c_y'])} N/m, "
          f"d_y = {_fmt(effective['d_y'])} N·s/m")
    print(f"  y_max = {last['y_max'] * 1e3:.4g} mm (eps_y = {EPS_Y * 1e3:g} mm), "
          f"v_y_max = {last['v_y_max'] * 1e3:.4g} mm/s (eps_v = {EPS_V * 1e3:g} mm/s), "
          f"t_eq = {_fmt(last['t_eq'])} s")
    print(f"wrote {csv_path}")
    print(f"wrote {png_path}")
    return 0


def _headroom(ax, data, threshold: float) -> None:
    """Leave room above the curve and the threshold line so that neither hides under the title
    or a legend."""
    import numpy as np
    finite = np.asarray(data)[np.isfinite(data)]
    top = max(float(finite.max()) if finite.size else 0.0, threshold)
    bottom = min(float(finite.min()) if finite.size else 0.0, 0.0)
    span = top - bottom
    ax.set_ylim(bottom - 0.05 * span, top + 0.2 * span)


def _load_case(params: dict) -> str:
    if int(params.get("mode", 1)) == 2:
        if params.get("use_y_in"):
            return "Motion-driven pullout, y prescribed by the input y_in"
        return (f"Motion-driven pullout at v_pull = {params.get('v_pull', float('nan')) * 6e4:.4g} mm/min")
    return (f"Pullout, F_pull ramped to F_max = {_fmt(params.get('F_max', float('nan')))} N over "
            f"t_ramp = {_fmt(params.get('t_ramp', float('nan')))} s")


def plot_pullout(df, params: dict, path: Path) -> None:
    """Three stacked panels: forces, displacement and velocity against time, with Table 2's
    thresholds."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = df["time"].to_numpy()
    t_eq = float(df["t_eq"].iloc[-1])
    fig, axes = plt.subplots(3, 1, figsize=(7.0, 8.0), sharex=True, constrained_layout=True)
    fig.suptitle(f"{_load_case(params)}\n"
                 f"c = c_y = {_fmt(params.get('c_y', float('nan')))} N/m,  "
                 f"d = d_y = {_fmt(params.get('d_y', float('nan')))} N·s/m", fontsize=12)

    ax = axes[0]
    motion = int(params.get("mode", 1)) == 2
    ax.plot(t, df["F_pull"], lw=2, color="tab:red",
            label="drive reaction $F_{pull}$" if motion else "pullout force $F_{pull}$")
    ax.plot(t, df["F_y"], lw=1.2, ls="--", color="k",
            label="interface force $F_y = c_y y + d_y \\dot y$")
    ax.set_ylabel("force [N]")

    ax = axes[1]
    y_mm = df["y"].to_numpy() * 1e3
    ax.plot(t, y_mm, lw=2, color="tab:blue", label="displacement $y$")
    ax.axhline(EPS_Y * 1e3, color="tab:purple", ls="--", lw=1.2,
               label=f"threshold $\\epsilon_y$ = {EPS_Y * 1e3:g} mm (Table 2)")
    ax.set_ylabel("displacement y [mm]")
    _headroom(ax, y_mm, EPS_Y * 1e3)

    ax = axes[2]
    v = df["v_y"].to_numpy() * 1e3
    ax.plot(t, v, lw=2, color="tab:green", label="velocity $\\dot y$")
    ax.axhline(EPS_V * 1e3, color="tab:purple", ls="--", lw=1.2,
               label=f"threshold $\\epsilon_{{\\dot y}}$ = {EPS_V * 1e3:g} mm/s (Table 2)")
    if (v < 0).any():
        ax.axhline(-EPS_V * 1e3, color="tab:purple", ls="--", lw=1.2)
    ax.set_ylabel("velocity $\\dot y$ [mm/s]")
    ax.set_xlabel("time t [s]")
    _headroom(ax, v, EPS_V * 1e3)

    for ax in axes:
        ax.grid(True, alpha=0.3)
        if t_eq >= 0:
            ax.axvline(t_eq, color="0.35", ls=":", lw=1.3,
                       label=f"at rest from $t_{{eq}}$ = {t_eq:.6g} s" if ax is axes[2] else None)
    rest = "" if t_eq >= 0 else "\nnot at rest at the end ($t_{eq}$ = -1)"
    axes[0].legend(loc="best", fontsize=9)
    axes[1].legend(loc="best", fontsize=9, title_fontsize=9,
                   title=f"max |y| = {df['y_max'].iloc[-1] * 1e3:.4g} mm")
    axes[2].legend(loc="best", fontsize=9, title_fontsize=9,
                   title=f"max |$\\dot y$| = {df['v_y_max'].iloc[-1] * 1e3:.4g} mm/s{rest}")
    from fmusa.files import save_figure

    save_figure(fig, path, tight=False, dpi=120)


# ---------------------------------------------------------------------------- sweep
def _add_sweep(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep", help="run a study file: grid, region of interest, search, regression, sensitivity",
        description="Run every stage of a study (YAML) and write runs.csv, summary.json, figures/ and "
                    "report.md into --out.")
    p.add_argument("study", type=Path, help="the study file, e.g. studies/paper.yaml")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted study in --out: runs already in runs.csv are not redone")
    p.add_argument("--retry-failed", action="store_true",
                   help="with --resume: run the failed runs of runs.csv again (a crash or memory fault that "
                        "may not repeat); the runs that worked are kept")
    p.add_argument("--workers", type=_int_at_least(1), default=None,
                   help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask distributed scheduler (e.g. tcp://127.0.0.1:8786) to run on")
    p.add_argument("--no-figures", action="store_true", help="skip figures and report.md")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_sweep)


def cmd_sweep(args: argparse.Namespace) -> int:
    from fmusa.api import load_study, run_study     # load_study: with the applications' blocks checked

    if args.retry_failed and not args.resume:
        raise UsageError("--retry-failed reruns the failed runs of a study in --out: give it with --resume")
    from fmusa.study.loader import files_outside

    study = load_study(args.study)
    for note in files_outside(study):    # the study file may come from someone else: say what it reads
        print(f"note: {note}", file=sys.stderr)

    def kept() -> set[Path]:
        """The run files an earlier study left aside: runs.csv and the sensitivity stage's alike (a study with a
        sensitivity stage only has no runs.csv)."""
        return set(args.out.glob("*runs.previous-*.csv")) if args.out.is_dir() else set()

    before = kept()
    try:
        result = run_study(study, args.out, resume=args.resume, workers=args.workers, scheduler=args.scheduler,
                           figures=not args.no_figures, progress=not args.quiet, retry_failed=args.retry_failed)
    finally:   # said once it has happened (a study that fails to start moves nothing), --quiet or not
        _note_kept(args.out, sorted(kept() - before))
    s = result.summary
    counts = s.get("run_counts") or {}          # the one count of runs (docs: runs and how they are counted)
    print(f"{study.name}: {counts.get('runs', 0)} runs ({counts.get('simulated_now', 0)} simulated now, "
          f"{counts.get('failed', 0)} failed) in {s.get('wall_s', 0.0):.2f} s")
    if s.get("optimum"):
        opt = ", ".join(f"{k} = {v:.6g}" for k, v in s["optimum"].items())
        print(f"optimum: {opt}; binding: {', '.join(s.get('binding_constraint') or []) or 'none'}"
              + ("" if s.get("optimum_reliable", True) else " (unreliable: see the warnings)"))
    for note in s.get("optimum_at_edge") or []:
        print(f"note: {note}")
    for note in (s.get("optimum_free") or {}).values():
        print(f"note: {note}")
    acc = s.get("accuracy")
    if acc:      # a check after the stages moved a metric a constraint reads
        print(f"warning: the accuracy checks moved the constrained metric{'s' if len(acc['metrics']) > 1 else ''} "
              f"{', '.join(acc['metrics'])}: every run's feasibility"
              f"{' and the optimum' if s.get('optimum') else ''} may be wrong", file=sys.stderr)
        for w in acc["warnings"][:3]:
            print(f"  {w}", file=sys.stderr)
        if len(acc["warnings"]) > 3:
            print(f"  ({len(acc['warnings']) - 3} more in summary.json, key accuracy)", file=sys.stderr)
    par = (s.get("search") or {}).get("parallel")
    if par:      # the search in rounds (search.parallel): its rounds against the sequential search's
        print(f"search: {par['runs']} points asked in {par['rounds']} rounds of up to {par['workers']}; the "
              f"sequential search asks for {par['sequential_rounds']}, one per round")
    for note in (s.get("sensitivity") or {}).get("messages") or []:    # the sensitivity stage's notes (SALib's warnings among them)
        print(f"sensitivity: {note}")
    for name in ("runs.csv", "summary.json", "report.md"):
        if (args.out / name).exists():
            print(f"wrote {args.out / name}")
    return 0


def _note_kept(out: Path, paths: list[Path]) -> None:
    """One note per earlier study moved aside: its run files and the outputs that went with them."""
    by_tag: dict[str, list[Path]] = {}
    for path in paths:
        by_tag.setdefault(path.stem.rpartition(".")[2], []).append(path)        # previous-<n>
    for tag, runs in sorted(by_tag.items()):
        names = {p.name for p in runs} | {p.name + ".study.json" for p in runs}
        aside = sorted(p.name for p in out.glob(f"*.{tag}*") if p.name not in names
                       and p.name.partition(f".{tag}")[2][:1] in ("", "."))     # not previous-10 for -1
        also = f" (and its {', '.join(aside)})" if aside else ""
        print(f"note: this study started afresh; the earlier runs are kept in {', '.join(map(str, runs))}{also} "
              f"(use --resume to continue a study instead)", file=sys.stderr)


# ---------------------------------------------------------------------------- inspect
CAUSALITIES = ("parameter", "calculatedParameter", "input", "output", "local", "independent")
_COLUMNS = ("name", "causality", "variability", "type", "unit", "start", "description")


def _add_inspect(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect", help="show what an FMU offers: FMI version, interfaces, binaries, sources, variables",
        description="Print an FMU's FMI version, model name, interfaces (co-simulation CS, model exchange ME), "
                    "the platforms it has binaries for, whether it carries its C sources, its default "
                    "experiment, and a table of its variables (name, causality, variability, type, unit, "
                    "start, description). Use it to write a study's mapping: study parameters and 'fixed' "
                    "need causality parameter with variability fixed or tunable, 'scenario.inputs' need "
                    "causality input, metrics read outputs.")
    p.add_argument("fmu", type=Path, metavar="FMU", help="an .fmu file or an extracted FMU directory")
    p.add_argument("--causality", action="append", metavar="KIND", dest="causality",
                   help="only variables of this causality (repeatable or comma-separated): "
                        + ", ".join(CAUSALITIES))
    p.add_argument("--name", metavar="PATTERN", default=None,
                   help="only variables whose name matches PATTERN (shell wildcards, e.g. 'c_*'; a plain word "
                        "matches anywhere in the name)")
    p.add_argument("--csv", action="store_true",
                   help="print the variable table as CSV (all columns, nothing truncated) and nothing else")
    p.add_argument("--full", action="store_true", help="do not truncate long descriptions")
    p.set_defaults(func=cmd_inspect)


def _causalities(items: list[str] | None) -> set[str] | None:
    if not items:
        return None
    out = set()
    lower = {c.lower(): c for c in CAUSALITIES}
    for item in items:
        for word in filter(None, (w.strip() for w in item.split(","))):
            c = lower.get(word.lower())
            if c is None:
                import difflib
                close = difflib.get_close_matches(word, CAUSALITIES, n=1)
                hint = f"; did you mean {close[0]}?" if close else ""
                raise UsageError(f"unknown causality {word!r}{hint} (known: {', '.join(CAUSALITIES)})")
            out.add(c)
    return out


def _variable_rows(info, causality: set[str] | None, pattern: str | None) -> list[dict[str, str]]:
    import fnmatch
    rows = []
    for v in info.variables:
        c = v.causality or "local"
        if causality is not None and c not in causality:
            continue
        if pattern and not (fnmatch.fnmatchcase(v.name, pattern) if any(ch in pattern for ch in "*?[")
                            else pattern.lower() in v.name.lower()):
            continue
        unit = v.unit or (v.declaredType.unit if getattr(v, "declaredType", None) is not None else None) or ""
        typ = getattr(v, "fmi3_type", None) or v.type or ""   # FMI 3.0: its own type names (Float64…)
        if typ == "Enumeration" and getattr(v, "declaredType", None) is not None and v.declaredType.name:
            typ = f"Enumeration({v.declaredType.name})"
        rows.append({"name": v.name, "causality": c, "variability": v.variability or "continuous",
                     "type": typ, "unit": unit, "start": _fmt_start(v.start),
                     "description": " ".join((v.description or "").split())})
    return rows


def _fmt_start(start) -> str:
    """The start value as declared; long numbers shortened to 10 (or 7) significant digits."""
    if start is None:
        return ""
    text = str(start)
    if len(text) > 12:
        try:
            x = float(text)
        except ValueError:
            return text
        text = f"{x:.10g}"
        if len(text) > 14:
            text = f"{x:.7g}"
    return text


def _table(rows: list[dict[str, str]], width: int, full: bool) -> list[str]:
    """Aligned columns; long names and starts are cut at a cap, descriptions at the terminal width."""
    caps = {"name": 48, "causality": 19, "variability": 11, "type": 24, "unit": 14, "start": 16}

    def cut(text: str, n: int) -> str:
        return text if len(text) <= n else text[:max(1, n - 1)] + "…"

    widths = {}
    for col in _COLUMNS[:-1]:
        widths[col] = max([len(col)] + [len(r[col]) for r in rows])
        if not full:
            widths[col] = min(widths[col], caps[col])
    used = sum(widths[c] + 2 for c in _COLUMNS[:-1])
    desc = max([len("description")] + [len(r["description"]) for r in rows])
    if not full:
        desc = min(desc, max(12, width - used))
    widths["description"] = desc
    lines = ["  ".join(col.ljust(widths[col]) for col in _COLUMNS).rstrip(),
             "  ".join("-" * widths[col] for col in _COLUMNS)]
    for r in rows:
        lines.append("  ".join((r[c] if full else cut(r[c], widths[c])).ljust(widths[c])
                               for c in _COLUMNS).rstrip())
    return lines


def _fmt_num(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _sources_line(info, full: bool) -> str:
    """The C sources in one line: how many, a few names (all with --full), and whether fmusa can build them."""
    if info.can_compile:
        files = list(info.source_files)
        shown = files if full or len(files) <= 4 else files[:3] + ["…"]
        text = f"{len(files)} file{'s' * (len(files) != 1)} listed under <SourceFiles> ({', '.join(shown)})"
        if not full and len(files) > 4:
            text += "; --full lists them"
        return text
    if info.has_sources:
        if info.is_fmi3:
            return "sources/ present (fmusa builds binaries from sources for FMI 2.0 only)"
        return "sources/ present, but not listed under <SourceFiles> (fmusa cannot build them)"
    return "none"


def _runs_here(info, note: str | None) -> str:
    """Whether fmusa can run the FMU on this machine, and why not: its FMI version, and whether the binary
    for this machine is there and loads (asked of a child process), or can be built from its sources."""
    from fmusa.fmi.loadable import binary_loads
    from fmusa.runs.preflight import load_problem

    if note:           # an FMI version fmusa does not run (FMI 1.0): the reader's message says which and why
        return (f"no: FMI {info.fmi_version}; fmusa runs FMI {' and '.join(SUPPORTED_FMI_VERSIONS)} FMUs: export "
                f"the model again as one")
    plat = info.host_platform
    with_binary = [i for i in info.interfaces if info.has_binary(i)]
    if not info.interfaces:
        return "no: the model description declares no co-simulation or model exchange interface"
    if not with_binary:
        if info.can_compile:
            return (f"once built: no {plat} binary; fmusa builds one from the C sources before the first run "
                    f"(this needs a C compiler)")
        return (f"no: no {plat} binary (it has {', '.join(info.platforms) or 'none'}) and no C sources to build "
                f"one from: export it again for this platform, or with its C sources")
    answers = {}
    for iface in with_binary:
        name = info.binary_name(iface)
        answers.setdefault(name, (iface, binary_loads(info, iface)))
    bad = [(i, a) for i, a in answers.values() if a is not None and not a.loads]
    label = {"co-simulation": "co-simulation", "model-exchange": "model exchange"}
    modes = " and ".join(label.get(i, i) for i in with_binary)
    if not bad:
        return f"yes: FMI {info.fmi_version}, {modes}; the {plat} binary loads"
    iface, answer = bad[0]
    reason = load_problem(str(info.path), Exception(answer.reason)).split(": the FMU cannot be loaded on this "
                                                                          "machine: ", 1)[-1]
    return f"no: the {plat} binary does not load: {reason}"


def cmd_inspect(args: argparse.Namespace) -> int:
    import shutil as _shutil

    from fmusa.fmi.info import FMUError, read_fmu_info

    causality = _causalities(args.causality)
    note = None
    try:
        info = read_fmu_info(args.fmu)
    except FMUError as exc:
        if "needs FMI 2.0" not in str(exc):
            raise
        note = str(exc)
        try:
            info = read_fmu_info(args.fmu, require_fmi2=False)
        except Exception:
            raise FMUError(note) from None
    rows = _variable_rows(info, causality, args.name)
    if args.csv:
        import csv
        w = csv.DictWriter(sys.stdout, fieldnames=list(_COLUMNS), lineterminator="\n")
        try:
            w.writeheader()
            w.writerows(rows)
            sys.stdout.flush()
        except BrokenPipeError:
            _quiet_stdout()
        if note:
            print(f"fmusa inspect: {note}", file=sys.stderr)
        if info.unsafe:
            print(f"fmusa inspect: UNSAFE: {'; '.join(info.unsafe)}: fmusa refuses to build or run this FMU",
                  file=sys.stderr)
        return 0
    plat = info.host_platform
    names = {"co-simulation": "co-simulation (CS)", "model-exchange": "model exchange (ME)"}
    ifaces = ", ".join(f"{names.get(k, k)}, model identifier {v}" for k, v in info.interfaces.items()) or "none"
    binaries = ", ".join(info.platforms) if info.platforms else "none"
    sources = _sources_line(info, args.full)
    de = info.default_experiment
    if de:
        parts = [f"{label} {_fmt_num(de[key])}{unit}" for key, label, unit in
                 (("start_time", "start", " s"), ("stop_time", "stop", " s"), ("step_size", "step", " s"),
                  ("tolerance", "tolerance", "")) if key in de]
        experiment = ", ".join(parts)
    else:
        experiment = "none"
    counts: dict[str, int] = {}
    for v in info.variables:
        c = v.causality or "local"
        counts[c] = counts.get(c, 0) + 1
    summary = ", ".join(f"{counts[c]} {c}" for c in CAUSALITIES if c in counts)
    if not counts.get("parameter"):
        summary += ("; no parameters: a study can set only its inputs" if counts.get("input") else
                    "; no parameters and no inputs: a study can set nothing")
    head = [
        ("file", str(args.fmu)),
        ("FMI version", info.fmi_version),
        ("runs here", _runs_here(info, note)),
        ("model name", info.model_name),
        ("description", info.description or "-"),
        ("generated by", info.generation_tool or "-"),
        ("interfaces", ifaces),
        ("binaries", binaries),
        ("sources", sources),
        ("default experiment", experiment),
    ]
    if "model-exchange" in info.interfaces:
        head.append(("ME states / events", f"{info.n_states} continuous states, "
                                           f"{info.n_event_indicators} event indicators"))
    if info.is_fmi3:   # arrays are listed element-wise, as a study addresses them
        arrays = [v for v in info.declared_variables if v.shape]
        head.append(("variables", f"{len(info.variables)} scalars ({summary}) in "
                                  f"{len(info.declared_variables)} variables, {len(arrays)} of them arrays"))
        if arrays:
            head.append(("arrays", "; ".join(
                f"{v.name} ({'×'.join(map(str, v.shape))}, {v.causality or 'local'}): "
                f"{v.name}[{','.join('1' * len(v.shape))}] … {v.name}[{','.join(map(str, v.shape))}]"
                for v in arrays) + "  (elements 1-based, as a study names them)"))
    else:
        head.append(("variables", f"{len(info.variables)} ({summary})"))
    if info.unsafe:      # names that lead outside the folder: said here, refused by sweep, diagnose, pullout
        head.append(("UNSAFE", "; ".join(info.unsafe) + ": fmusa refuses to build or run this FMU"))
    # an FMU's text may hold terminal control sequences: shown, not obeyed
    from fmusa.format import printable
    head = [(k, printable(v)) for k, v in head]
    rows = [{k: printable(v) for k, v in r.items()} for r in rows]
    width = _shutil.get_terminal_size((120, 24)).columns
    try:
        _print_inspect(head, info, note, rows, causality, args, width)
        sys.stdout.flush()
    except BrokenPipeError:   # e.g. `fmusa inspect X | head`: stop quietly
        _quiet_stdout()
    return 0


def _quiet_stdout() -> None:
    """After a closed pipe: send the rest of stdout (and Python's final flush) to /dev/null."""
    import os
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _print_inspect(head, info, note, rows, causality, args, width) -> None:
    import textwrap
    key_w = max(len(k) for k, _ in head)
    for k, v in head:
        if args.full or len(v) + key_w + 2 <= width:
            print(f"{k.ljust(key_w)}  {v}")
        else:   # wrap long values under themselves
            print(textwrap.fill(v, width=max(40, width), initial_indent=f"{k.ljust(key_w)}  ",
                                subsequent_indent=" " * (key_w + 2)))
    for w in info.warnings:
        print(f"{'warning'.ljust(key_w)}  {' '.join(w.split())}")
    print()
    if not rows:
        filt = []
        if causality:
            filt.append("causality " + ", ".join(sorted(causality)))
        if args.name:
            filt.append(f"name {args.name!r}")
        print(f"no variables match {' and '.join(filt)}")
        return
    for line in _table(rows, width, args.full):
        print(line)
    if causality or args.name:
        print(f"({len(rows)} of {len(info.variables)} variables)")


# ---------------------------------------------------------------------------- diagnose
def _add_diagnose(sub: argparse._SubParsersAction, full: bool = True) -> None:
    """The diagnose subcommand; its options only when ``full`` (they need the candidate effects, an import
    that ``fmusa --help`` and the other subcommands do without)."""
    p = sub.add_parser(
        "diagnose", help="calibrate the model to measured tests, name the missing effect, measure the gain",
        description="Fit the baseline spring-damper and every candidate effect to one or more measured "
                    "tests (CSV, fitted jointly) by simulating the FMU with the measured drive; rank the "
                    "candidates on held-out data and by information criteria; write diagnosis.json, "
                    "figures/ and report.md into --out.")
    p.set_defaults(func=cmd_diagnose)
    if not full:
        return
    from fmusa.diagnose.effects import CANDIDATES

    p.add_argument("files", nargs="+", type=Path, metavar="STUDY.yaml | FILE.csv",
                   help="a diagnosis study file (the FMU, the tests, how they drive it, where the effects go), "
                        "or the measured tests of a model with a built-in description (ScrewVertebra), one per file")
    p.add_argument("--drive", default=None, choices=("force", "displacement"),
                   help="with CSV files: the channel the test imposed; the model is driven by it and predicts the "
                        "other")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    g = p.add_argument_group("columns and units (default: time,displacement,force in s, m, N)")
    g.add_argument("--time-column", default="time", metavar="NAME")
    g.add_argument("--displacement-column", default="displacement", metavar="NAME")
    g.add_argument("--force-column", default="force", metavar="NAME")
    g.add_argument("--time-unit", default="s", metavar="UNIT", help="s, ms or min")
    g.add_argument("--displacement-unit", default="m", metavar="UNIT", help="m, cm, mm, um")
    g.add_argument("--force-unit", default="N", metavar="UNIT", help="N, kN, mN, lbf")
    g.add_argument("--rate", default=None, metavar="RATE",
                   help="constant drive rate, e.g. '10 mm/s', to derive time for files without a time column")
    g.add_argument("--delimiter", default=None, type=_delimiter, metavar="CHAR",
                   help="field delimiter: ',' ';' '|' or tab (default: detected from each file)")
    g.add_argument("--decimal", default=None, choices=(".", ","),
                   help="decimal mark: '.' or ',' (default: detected from each file)")
    g.add_argument("--no-zero-drive", action="store_true",
                   help="keep the drive as measured (default: shift it to start at 0, where the model is at rest)")
    p.add_argument("--max-points", type=_int_at_least(10), default=300,
                   help="block-average each test to at most this many samples for the fit (default 300)")
    p.add_argument("--candidates", default=",".join(CANDIDATES),
                   help=f"comma-separated subset of: {', '.join(CANDIDATES)}")
    p.add_argument("--starts", type=_int_at_least(1), default=6, help="least-squares starts per model (default 6)")
    p.add_argument("--workers", type=_int_at_least(1), default=None, help="processes (default: all cores)")
    p.add_argument("--max-runs", type=_int_at_least(1), default=None, metavar="N",
                   help="the most FMU runs the diagnosis may make (default: no limit); when they end, the "
                        "candidates not fitted are left out and named in the report")
    p.add_argument("--fmu", type=Path, default=None,
                   help="with CSV files: an FMU of a model fmusa has a description of (ScrewVertebra; default "
                        "dist/ScrewVertebra.fmu); for any other FMU write a diagnosis study file")


#: The options of ``diagnose`` that a study file sets itself (its tests and diagnosis sections).
_STUDY_SETS = {"drive": None, "time_column": "time", "displacement_column": "displacement", "force_column": "force",
               "time_unit": "s", "displacement_unit": "m", "force_unit": "N", "rate": None, "no_zero_drive": False,
               "max_points": 300, "candidates": None, "starts": 6, "fmu": None}


def _diagnose_study(args: argparse.Namespace) -> dict:
    """``fmusa diagnose STUDY.yaml``: the study file sets the tests and the model; only --workers and --out."""
    from fmusa.diagnose.effects import DiagnoseError
    from fmusa.diagnose.run import run_study_diagnosis
    from fmusa.diagnose.study import load_diagnosis_study

    if len(args.files) != 1:
        raise DiagnoseError(f"give one diagnosis study file, or CSV files; got {len(args.files)} files with "
                         f"{args.files[0]}")
    given = [k for k, default in _STUDY_SETS.items() if getattr(args, k, default) != default
             and not (k == "candidates" and getattr(args, k) == _all_candidates())]
    if given:
        flags = ", ".join("--" + k.replace("_", "-") for k in given)
        raise DiagnoseError(f"{flags}: the study file {args.files[0]} sets these (its tests, effects and diagnosis "
                         f"sections); change them there")
    study = load_diagnosis_study(args.files[0])
    return run_study_diagnosis(study, args.out, workers=args.workers, max_runs=args.max_runs)


def _all_candidates() -> str:
    from fmusa.diagnose.effects import CANDIDATES

    return ",".join(CANDIDATES)


def cmd_diagnose(args: argparse.Namespace) -> int:
    from fmusa.diagnose.run import run_diagnosis
    from fmusa.diagnose.measured import ColumnSpec, load_experiments

    if args.files and args.files[0].suffix.lower() in (".yaml", ".yml"):
        return _print_diagnosis(args, _diagnose_study(args))
    if args.drive is None:
        from fmusa.diagnose.effects import DiagnoseError

        raise DiagnoseError("--drive is required with CSV files: force or displacement (the channel the test "
                         "imposed); or give a diagnosis study file")
    if args.max_points < 10:
        raise ValueError(f"--max-points must be >= 10, got {args.max_points}")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    cands = tuple(c.strip() for c in args.candidates.split(",") if c.strip())
    spec = ColumnSpec(time=args.time_column, displacement=args.displacement_column, force=args.force_column,
                      time_unit=args.time_unit, displacement_unit=args.displacement_unit,
                      force_unit=args.force_unit, rate=args.rate, delimiter=getattr(args, "delimiter", None),
                      decimal=getattr(args, "decimal", None))
    exps = load_experiments(args.files, args.drive, spec, zero_drive=not args.no_zero_drive,
                            max_points=args.max_points)
    for e in exps:        # what was detected, so that a wrong guess is seen
        if e.meta.get("detected"):
            print(f"read {e.path}: {', '.join(e.meta['detected'])} (detected; set with --delimiter, --decimal)")
    diag = run_diagnosis(exps, args.drive, args.out, fmu_path=args.fmu, candidates=cands,
                         workers=args.workers, max_starts=args.starts, max_runs=args.max_runs)
    return _print_diagnosis(args, diag)


def _print_diagnosis(args: argparse.Namespace, diag: dict) -> int:
    """The verdict on the terminal, and where the files are (parameters under the FMU's variable names)."""
    from fmusa.diagnose.report import fmu_name

    g = diag["gain"]
    print(f"effect: {diag['effect']}")
    if diag["effect"] != "none":
        ps = ", ".join(f"{fmu_name(diag, k)} = {v['value']:.4g}{'' if v['unit'] in ('', '1') else ' ' + v['unit']} "
                       f"[{v['ci95'][0]:.4g}, {v['ci95'][1]:.4g}]"
                       for k, v in diag["effect_params"].items())
        print(f"  {ps}")
        print(f"  rmse ratio {g['rmse_ratio']:.3f}, held-out rmse ratio {g['heldout_rmse_ratio']:.3f}, "
              f"delta AIC {g['delta_aic']:.1f}")
    final = diag.get("final") or {}
    if len(final.get("effects") or []) > 1:
        print(f"final model: baseline + {' + '.join(final['effects'])} (RMSE {final['rmse']:.4g}, held-out "
              f"{final['heldout_rmse']:.4g}; intervals: {(final.get('intervals') or {}).get('method', '?')})")
        print("  " + ", ".join(f"{fmu_name(diag, k)} = {v['value']:.4g}{'' if v['unit'] in ('', '1') else ' ' + v['unit']} "
                               f"[{v['ci95'][0]:.4g}, {v['ci95'][1]:.4g}]" for k, v in final["params"].items()))
    for r in diag.get("chain_removed") or []:
        print(f"  not added: {r['effect']} (step {r['step']}): {r['reason']}")
    for t in diag["indistinguishable"]:
        print(f"  cannot be told from {t['effect']}: {t['separating_test']}")
    if diag["leftover"]:
        print(f"  left in the residuals: {diag['leftover']}")
    cp = diag.get("coupling")
    if cp:
        print(f"  coupled runs: {cp['scheme']}, {cp['calls']} FMU calls and {cp['cpu_s']:.2f} s CPU for one run of "
              f"{cp['experiment']}")
    runs = diag["runs"]
    print(f"FMU runs: {runs['total']}" + (f" of a budget of {runs['budget']}" if runs["budget"] else "")
          + (f"; the budget ended, left out: {', '.join(runs['left_out'])}" if runs["left_out"] else ""))
    for name in ("diagnosis.json", "report.md"):
        if (args.out / name).exists():
            print(f"wrote {args.out / name}")
    return 0


def _add_diagnose_shear(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "diagnose-shear", help="diagnose the C6/C7 shear tests of data/shear-c67 and compare with the authors",
        description="Run `diagnose` on each specimen and direction of the shear-c67 data (all rates of a "
                    "unit jointly; the first --diagnosed specimens, or --all), fit every test's two lines as the "
                    "authors did and compare with their breakpoint analysis (test_info.csv; tuning and held-out "
                    "specimens apart) and across rates. Writes DIR/report.md, "
                    "DIR/summary.json, DIR/bilinear_comparison.csv and one diagnosis folder per unit.")
    p.add_argument("--data", type=Path, default=Path("data/shear-c67"), metavar="FOLDER",
                   help="the shear-c67 folder: H01/…, test_info.csv (default: data/shear-c67, relative to "
                        "the current directory)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    p.add_argument("--specimens", default=None, metavar="H1,H2",
                   help="comma-separated specimens to diagnose (default: every one in --data)")
    p.add_argument("--max-points", type=_int_at_least(10), default=300,
                   help="samples per test after block averaging")
    p.add_argument("--diagnosed", type=_int_at_least(1), default=3, metavar="N",
                   help="diagnose the first N specimens through the FMU (default 3; a specimen is two units, "
                        "and `make bench` times one: diagnose_shear_unit_wall_s); the two-line comparison with "
                        "the authors always covers every test")
    p.add_argument("--all", action="store_true", help="diagnose every specimen through the FMU (slow)")
    p.add_argument("--starts", type=_int_at_least(1), default=6, help="least-squares starts per model (default 6)")
    p.add_argument("--workers", type=_int_at_least(1), default=None, help="processes (default: all cores)")
    p.add_argument("--fmu", type=Path, default=None,
                   help="with CSV files: an FMU of a model fmusa has a description of (ScrewVertebra; default "
                        "dist/ScrewVertebra.fmu); for any other FMU write a diagnosis study file")
    p.set_defaults(func=cmd_diagnose_shear)


def cmd_diagnose_shear(args: argparse.Namespace) -> int:
    from fmusa.applications.shear_c67.study import run_shear_diagnosis

    specimens = [x.strip() for x in args.specimens.split(",") if x.strip()] if args.specimens else None
    s = run_shear_diagnosis(args.out, root=args.data, fmu_path=args.fmu, max_points=args.max_points,
                            workers=args.workers, max_starts=args.starts, specimens=specimens,
                            diagnosed=None if args.all else args.diagnosed)
    for k, g in s["groups"].items():
        print(f"{k}: {g['effect']}" + (f" (cannot be told from {', '.join(g['indistinguishable'])})"
                                       if g["indistinguishable"] else ""))
    print(f"wrote {args.out / 'report.md'}")
    return 0


# ---------------------------------------------------------------------------- entry point
#: The subcommands, each added to the parser by its ``_add_`` function.
COMMANDS = ("pullout", "sweep", "inspect", "diagnose", "diagnose-shear")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``fmusa`` parser. ``command``: the subcommand about to run, when known; a subcommand whose
    options need a heavy import (diagnose) defines them only when it is that one or ``command`` is None."""
    parser = argparse.ArgumentParser(
        prog="fmusa", description="Run the ScrewVertebra FMU (or another FMI "
                                  f"{' or '.join(SUPPORTED_FMI_VERSIONS)} FMU, co-simulation or model exchange) "
                                  "for parameter studies.")
    parser.add_argument("--version", action="version", version=f"fmusa {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    _add_pullout(sub)
    _add_sweep(sub)
    _add_inspect(sub)
    _add_diagnose(sub, full=command in (None, "diagnose"))
    _add_diagnose_shear(sub)
    return parser


def _command_word(argv: list[str]) -> str:
    """The subcommand named in ``argv`` ("" when none: ``fmusa --help``); the top-level parser has no
    option that takes a value, so it is the first word that is not an option."""
    return next((a for a in argv if not a.startswith("-")), "")


def _printable_console() -> None:
    """Make stdout and stderr print what their encoding cannot hold as escapes (``\\u0394`` for Δ) rather
    than end the command with UnicodeEncodeError: a Windows console in cp1252, or ``LC_ALL=C`` on POSIX,
    cannot encode the Δ, ≥ or Ü of a message. Files fmusa writes are UTF-8 whatever the console."""
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None and (getattr(stream, "encoding", "") or "").lower().replace("-", "") != "utf8":
            try:
                reconfigure(errors="backslashreplace")
            except (ValueError, OSError):   # a stream that cannot be reconfigured (detached, closed)
                pass


class Terminated(BaseException):
    """SIGTERM, raised in the main thread like KeyboardInterrupt, so that every ``finally`` (workers
    stopped, files closed) runs before the command exits with 143."""


def _stop_on_signals() -> dict:
    """SIGINT and SIGTERM raise (KeyboardInterrupt, :class:`Terminated`) once; a second one while the
    command cleans up is ignored, so the cleanup is not cut short (it is bounded: workers are killed).
    Returns the handlers it replaced (restored by :func:`main` when the command ends)."""
    import signal

    previous: dict = {}

    def handler(signum, frame):
        for s in (signal.SIGINT, getattr(signal, "SIGTERM", None)):
            if s is not None:
                try:
                    signal.signal(s, signal.SIG_IGN)
                except (OSError, ValueError):
                    pass
        raise Terminated() if signum != signal.SIGINT else KeyboardInterrupt()

    for s in (signal.SIGINT, getattr(signal, "SIGTERM", None)):
        if s is None:
            continue
        try:
            old = signal.getsignal(s)
            if old in (signal.SIG_DFL, signal.default_int_handler):
                signal.signal(s, handler)
                previous[s] = old
        except (OSError, ValueError):     # not the main thread, or a platform without it
            pass
    return previous


def _complete_lines(path: Path) -> int:
    """Data rows of a runs file (complete lines after the header; a torn last line is not one)."""
    try:
        with open(path, "rb") as fh:
            n = sum(chunk.count(b"\n") for chunk in iter(lambda: fh.read(1 << 20), b""))
    except OSError:
        return 0
    return max(0, n - 1)


def interrupted_message(args: argparse.Namespace) -> str:
    """What an interrupted command kept and how to continue: the runs on disk for ``sweep``, the cached
    fits for ``diagnose`` (reused by the same command)."""
    out = getattr(args, "out", None)
    out = Path(out) if out is not None else None
    if args.command == "sweep" and out is not None:
        n = _complete_lines(out / "runs.csv")
        m = _complete_lines(out / "sensitivity_runs.csv")
        extra = f" and {m} in sensitivity_runs.csv" if m else ""
        return f"interrupted: {n} runs kept in runs.csv{extra}; rerun with --resume to continue"
    if args.command in ("diagnose", "diagnose-shear") and out is not None:
        fits = sorted(out.rglob("fits/*.json")) if out.is_dir() else []
        return (f"interrupted: {len(fits)} fits kept in {out}; rerun the same command to continue (the kept "
                f"fits are reused)")
    return "interrupted"


def _one_line_warning(command: str):
    """A warning a library raises while a command runs (numpy, SALib, pandas…) as one line a user can read:
    what it says and which library said it, not the library's source path and line (the stages turn the
    warnings they expect into the study's own messages; this is for any other)."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        parts = Path(str(filename)).parts
        lib = next((p for p in reversed(parts[:-1]) if p in ("SALib", "numpy", "scipy", "pandas", "matplotlib",
                                                              "fmpy", "dask", "distributed", "fmusa")),
                   Path(str(filename)).stem)
        text = " ".join(str(message).split())
        try:
            print(f"fmusa {command}: warning: {text} ({category.__name__} from {lib})", file=file or sys.stderr)
        except (OSError, ValueError):
            pass
    return show


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand. A :class:`~fmusa.errors.FmusaError` is the user's to fix: one line on stderr
    and its ``exit_code`` (2, or 1 when an FMU could not be found, built or run); any other exception
    propagates with its traceback, as the bug it is. Ctrl-C and SIGTERM stop the command (its workers
    too) and print one line of what was kept: exit 130 and 143, as a shell reports those signals."""
    entry = argv is None          # the process's own command (console script, python -m fmusa.cli)
    argv = sys.argv[1:] if argv is None else list(argv)
    _printable_console()
    parser = build_parser(_command_word(argv))
    args = parser.parse_args(argv)
    previous = _stop_on_signals()
    import warnings
    shown = warnings.showwarning
    warnings.showwarning = _one_line_warning(args.command)
    try:
        return int(args.func(args) or 0)
    except FmusaError as exc:
        print(f"fmusa {args.command}: {exc}", file=sys.stderr)
        return exc.exit_code
    except (KeyboardInterrupt, Terminated) as exc:
        print(f"fmusa {args.command}: {interrupted_message(args)}", file=sys.stderr, flush=True)
        code = 143 if isinstance(exc, Terminated) else 130
        if entry:     # everything is stopped and closed (the finally blocks ran): no second of interpreter
            import os  # teardown (matplotlib, pandas, pool threads) between the line and the exit

            sys.stdout.flush()
            if "multiprocessing" in sys.modules:   # its finalizers (semaphores, queues), not the rest of exit
                try:
                    from multiprocessing import util

                    util._run_finalizers()
                except Exception:  # noqa: BLE001 - exiting anyway
                    pass
            sys.stderr.flush()
            os._exit(code)
        return code
    finally:
        import signal

        warnings.showwarning = shown
        for s, old in previous.items():
            try:
                signal.signal(s, old)
            except (OSError, ValueError):
                pass


if __name__ == "__main__":
    sys.exit(main())
