"""The paper's physics runs: how its results depend on the ramp time and the end time it does not state.

Run by :class:`~fmusa.applications.paper.extension.PaperExtension` after the study's stages (a few hundred
runs of well under a millisecond each) and kept as plain data (:class:`PaperPhysics`) for the paper's
report sections, which compute nothing. Every number of the "Deviations explained" section comes from here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import pandas as pd

from fmusa.analysis.bisect import FEASIBLE_AT_LO, crossing, smallest_feasible
from fmusa.analysis.roi import Region, automatic_region
from fmusa.fmi.plans import RunPlan
from fmusa.runs.metrics import metric_rules, reduce_series
from fmusa.runs.spec import PlanSpec, runner_for

__all__ = ["PaperScenario", "PaperPhysics", "ScenarioRunner", "compute_physics", "optimum_time_series"]

RAMPS = (0.1, 1.0, 10.0, 30.0)          # s, the ramp times of the ramp-time table (end = t_ramp + 2 s)
ENDS = (10.5, 11.0, 12.0, 20.0)         # s, the end times of the end-time table
SETTLE = 2.0                            # s after the ramp's end that every ramp scenario runs


@dataclass(frozen=True)
class PaperScenario:
    """The pullout's numbers as the study sets them: force, ramp time, the two thresholds, the axes."""
    F: float
    t_ramp: float
    eps_y: float
    eps_v: float
    inner: str
    outer: str

    @classmethod
    def of(cls, study, inner: str | None, outer: str | None) -> "PaperScenario | None":
        """The scenario when the study is the paper's force ramp with both thresholds, else None."""
        th = {c.metric: float(c.max) for c in study.constraints if c.max is not None}
        try:
            F, T = float(study.fixed["F_max"]), float(study.fixed["t_ramp"])
        except (KeyError, TypeError, ValueError):
            return None
        if "max_y" not in th or "max_v" not in th or inner not in study.parameters \
                or outer not in study.parameters or "t_eq" not in study.metrics:
            return None
        return cls(F, T, th["max_y"], th["max_v"], inner, outer)


@dataclass
class PaperPhysics:
    """The runs' results: one row per ramp-time and end-time scenario, the smallest feasible inner value
    against the ramp time, and the checks of the paper's printed numbers (``checks``, see the report)."""
    scen_ramp: list = field(default_factory=list)
    scen_stop: list = field(default_factory=list)
    ramp_curve: list = field(default_factory=list)        # [{"t_ramp", "c_min"}]
    checks: dict = field(default_factory=dict)
    runs: int = 0


# ============================================================================ one FMU, many scenarios
class ScenarioRunner:
    """Runs the study's FMU at single (inner, outer) points under a changed scenario (fixed parameters
    overridden, another end time), reducing the outputs to the study's metrics and checking its
    constraints as the pipeline does. One FMU instance; one prepared RunPlan per scenario."""

    def __init__(self, study, spec: PlanSpec, inner: str, outer: str) -> None:
        self.study, self.spec = study, spec
        self.inner, self.outer = inner, outer
        self.runner = runner_for(spec)
        self.outputs = list(dict.fromkeys(m.output for m in study.metrics.values()))
        self.rules = metric_rules(study.metrics.values(), self.outputs)
        self.names = [r.name for r in self.rules]
        self.varied = [study.parameters[inner].variable, study.parameters[outer].variable]
        self.plans: dict = {}
        self.runs = 0

    def close(self) -> None:
        self.runner.close()

    def plan(self, overrides: Mapping[str, float], stop: float) -> RunPlan:
        key = (tuple(sorted(overrides.items())), float(stop))
        if key not in self.plans:
            fixed = {**self.study.fixed, **overrides}
            self.plans[key] = RunPlan(self.runner, self.varied, fixed, self.outputs, stop,
                                      self.study.scenario.step, dict(self.study.scenario.inputs))
        return self.plans[key]

    def _row(self, c: float, d: float, values: np.ndarray | None, message: str = "") -> dict:
        st = self.study
        row = dict(zip(self.names, map(float, values))) if values is not None else {n: math.nan for n in self.names}
        row.update({self.inner: c, self.outer: d, "status": "ok" if values is not None else "failed"})
        if values is None:
            row["message"] = message[:300]
        feas = values is not None
        for con in st.constraints:
            ok = values is not None and con.satisfied(row[con.metric])
            row[f"ok_{con.name}"] = ok
            feas &= ok
        row["feasible"] = feas
        return row

    def __call__(self, c: float, d: float, overrides: Mapping[str, float] | None = None,
                 stop: float | None = None) -> dict:
        st = self.study
        stop = float(stop if stop is not None else st.scenario.stop_time)
        plan = self.plan(dict(overrides or {}), stop)
        self.runs += 1
        try:
            data = plan([st.parameters[self.inner].to_fmu(c), st.parameters[self.outer].to_fmu(d)])
        except Exception as exc:  # noqa: BLE001 - a failed run is a result too
            return self._row(c, d, None, str(exc))
        return self._row(c, d, reduce_series(plan.times, data, self.rules))

    def smallest_feasible(self, d: float, overrides=None, stop=None, lo: float = 1e3, hi: float = 1e11,
                          rtol: float = 1e-4) -> tuple[float | None, dict | None, dict | None]:
        """Smallest feasible inner value at outer value ``d`` (geometric bisection; the boundary is
        monotone, as the search assumes): (value, its run, the last infeasible run below)."""
        b = smallest_feasible(lambda x: self(x, d, overrides, stop), lo, hi, rtol,
                              feasible=lambda r: bool(r["feasible"]), midpoint="geometric")
        if b.status == FEASIBLE_AT_LO:
            return b.value, b.result, None
        return b.value, b.result, (b.below_result if b.value is not None else None)

    def grid_region(self, xs, zs, overrides=None, stop=None) -> tuple[Region | None, pd.DataFrame]:
        """The automatic region of interest of the grid xs × zs under a changed scenario."""
        df = pd.DataFrame([self(x, z, overrides, stop) for x in xs for z in zs])
        try:
            return automatic_region(df, self.inner, self.outer), df
        except ValueError:
            return None, df


# ============================================================================ the scenario tables
def scenario_row(sr: ScenarioRunner, c: float, d: float, T: float, stop: float, xs, zs, bisect: bool = True) -> dict:
    """Our optimum under ramp ``T`` and end ``stop``; the smallest feasible inner value there (``bisect``)
    and the grid's automatic region, rest count and mean/max translation ratio."""
    ov = {"t_ramp": T}
    row = {"t_ramp": T, "stop": stop, **sr(c, d, ov, stop)}
    if bisect:
        cmin, _, below = sr.smallest_feasible(d, ov, stop)
        row["c_min"] = cmin
        row["c_min_fails_below"] = (", ".join(con.name for con in sr.study.constraints
                                              if below is not None and not below[f"ok_{con.name}"]) or "–")
    reg, gdf = sr.grid_region(xs, zs, ov, stop)
    row["roi"] = reg
    ok = gdf[gdf["status"] == "ok"]
    row["grid_no_rest"] = int(ok["t_eq"].isna().sum()) if "t_eq" in ok else 0
    row["grid_feasible"] = int(ok["feasible"].sum())
    ratio = (ok["mean_y"] / ok["max_y"]) if {"mean_y", "max_y"} <= set(ok.columns) else pd.Series(dtype=float)
    row["grid_mean_over_max_y"] = float(np.nanmedian(ratio)) if len(ratio) else math.nan
    return row


def ramp_curve(sr: ScenarioRunner, d0: float) -> list[dict]:
    """The smallest feasible inner value at ``d0`` for 19 ramp times from 0.05 to 100 s."""
    curve = []
    for T in np.geomspace(0.05, 100, 19):
        cmin, _, _ = sr.smallest_feasible(d0, {"t_ramp": float(T)}, float(T) + SETTLE)
        curve.append({"t_ramp": float(T), "c_min": cmin if cmin is not None else math.nan})
    return curve


# ============================================================================ the paper's printed numbers
def _ramp(sr: ScenarioRunner, c: float, d: float, T: float) -> dict:
    return sr(c, d, {"t_ramp": T}, T + SETTLE)


def paper_optimum_checks(sr: ScenarioRunner, block: Mapping, sc: PaperScenario) -> dict:
    """At the paper's optimum: max(ẏ) per ramp time, the ramp that meets ε_ẏ, the ramp that reproduces the
    paper's t_eq, and the settling time after our ramp; the paper's second (c, d, t_eq) point."""
    popt = block.get("optimum") or {}
    if "c" not in popt or "d" not in popt:
        return {}
    cp, dp, T0 = float(popt["c"]), float(popt["d"]), sc.t_ramp
    pc: dict = {"paper_opt": (cp, dp),
                "paper_opt_by_ramp": {T: _ramp(sr, cp, dp, T) for T in (0.01, 0.1, 1.0, 5.0, 10.0, 30.0)},
                "T_for_eps_v": crossing(lambda T: _ramp(sr, cp, dp, T)["max_v"], sc.eps_v, 0.01, 1000.0, 1e-5,
                                        midpoint="geometric", increasing=False)}
    if popt.get("t_eq") is not None:
        pc["paper_t_eq"] = t_eq_p = float(popt["t_eq"])
        Tq = crossing(lambda T: _ramp(sr, cp, dp, T)["t_eq"], t_eq_p, 1e-5, 1.0, 1e-5, midpoint="geometric",
                      increasing=True)
        pc["T_for_t_eq"] = Tq
        if Tq is not None:
            pc["at_T_for_t_eq"] = _ramp(sr, cp, dp, Tq)
        pc["settle_after_ramp_T0"] = _ramp(sr, cp, dp, T0)["t_eq"] - T0
    second = block.get("t_eq_at_c_1562499_d_7813")
    if second is not None:
        c2, d2 = 1562499.0, 7813.0
        pc["second_point"] = (c2, d2, float(second))
        pc["second_t_eq_short"] = sr(c2, d2, {"t_ramp": 1e-5}, 2.0)["t_eq"]
        if pc.get("T_for_t_eq") is not None:
            pc["second_t_eq_at_Tq"] = _ramp(sr, c2, d2, pc["T_for_t_eq"])["t_eq"]
        pc["second_t_eq_T0"] = _ramp(sr, c2, d2, T0)["t_eq"]
    return pc


def _snap(x: float, axis) -> float:
    """The grid value the paper prints to 3 digits (1.56e4 for 25^3 = 15625), else ``x``."""
    axis = np.asarray(axis, float)
    k = int(np.argmin(np.abs(np.log(axis / x))))
    return float(axis[k]) if abs(axis[k] / x - 1) < 0.01 else float(x)


def max_v_extreme_checks(sr: ScenarioRunner, ext: Mapping, xs, zs) -> dict:
    """The ramp that reproduces the paper's largest grid velocity, and where the grid's velocity maximum
    lies under that ramp."""
    cv, dv, vv = _snap(float(ext["c"]), xs), _snap(float(ext["d"]), zs), float(ext["value"])
    Tv = crossing(lambda T: _ramp(sr, cv, dv, T)["max_v"], vv, 1e-3, 1000.0, 1e-5, midpoint="geometric",
                  increasing=False)
    pc: dict = {"max_v_ext": (cv, dv, vv, Tv)}
    Ts = np.geomspace(1e-3, 100.0, 16)
    d_lo = float(np.min(zs))
    if d_lo < dv:
        wins = [_ramp(sr, cv, d_lo, float(T))["max_v"] >= _ramp(sr, cv, dv, float(T))["max_v"] for T in Ts]
        pc["max_v_lower_d_wins"] = (d_lo, int(sum(wins)), len(Ts), float(Ts[0]), float(Ts[-1]))
    if Tv is not None:
        inner, outer = sr.inner, sr.outer
        g = pd.DataFrame([_ramp(sr, x, z, Tv) for x in xs for z in zs])
        k = g["max_v"].idxmax()
        pc["max_v_grid_at_Tv"] = (float(g.at[k, "max_v"]), float(g.at[k, inner]), float(g.at[k, outer]))
        pc["max_v_Tv_at_same_c"] = g[np.isclose(g[inner], cv)][[outer, "max_v"]].to_numpy().tolist()
        pc["grid_mean_over_max_y_Tv"] = float(np.nanmedian(g["mean_y"] / g["max_y"])) if "mean_y" in g else None
    return pc


def roi_checks(sr: ScenarioRunner, region: Region | None, grid: pd.DataFrame, xs, zs, T0: float) -> dict:
    """The grid cell whose rest decides the automatic region's top, and the region when the runs end
    before that cell is at rest."""
    if region is None:
        return {}
    inner, outer = sr.inner, sr.outer
    col = grid[np.isclose(grid[outer], region.outer_range[1]) & np.isclose(grid[inner], region.inner_range[1])]
    if not len(col):
        return {}
    pc = {"roi_top_cell_t_eq": float(col.iloc[0]["t_eq"])}
    t_top = pc["roi_top_cell_t_eq"]
    if math.isfinite(t_top) and t_top > T0:
        stop_b = T0 + 0.9 * (t_top - T0)
        reg_b, _ = sr.grid_region(xs, zs, {"t_ramp": T0}, stop_b)
        pc["roi_below_top_t_eq"] = (stop_b, reg_b)
    return pc


# ============================================================================ all of it
def _grid_axes(study, inner: str, outer: str, c0: float, d0: float) -> tuple[np.ndarray, np.ndarray]:
    axes = study.stages["grid"].points() if "grid" in study.stages else {inner: np.array([c0]), outer: np.array([d0])}
    return axes[inner], axes[outer]


def compute_physics(study, spec: PlanSpec, sc: PaperScenario, optimum: Mapping[str, float], region: Region | None,
                    runs: pd.DataFrame, block: Mapping) -> PaperPhysics:
    """Every physics run of the paper's report, on the study's prepared FMU."""
    c0, d0 = float(optimum[sc.inner]), float(optimum[sc.outer])
    xs, zs = _grid_axes(study, sc.inner, sc.outer, c0, d0)
    ph = PaperPhysics()
    sr = ScenarioRunner(study, spec, sc.inner, sc.outer)
    try:
        ph.scen_ramp = [scenario_row(sr, c0, d0, T, T + SETTLE, xs, zs) for T in RAMPS]
        ph.scen_stop = [scenario_row(sr, c0, d0, sc.t_ramp, stop, xs, zs, bisect=False)
                        for stop in ENDS if stop > sc.t_ramp]
        ph.ramp_curve = ramp_curve(sr, d0)
        ph.checks.update(paper_optimum_checks(sr, block, sc))
        ext = (block.get("grid_extremes") or {}).get("max_v")
        if isinstance(ext, Mapping):
            ph.checks.update(max_v_extreme_checks(sr, ext, xs, zs))
        ext_y = (block.get("grid_extremes") or {}).get("max_y")
        if isinstance(ext_y, Mapping):
            ph.checks["max_y_ext"] = (float(ext_y["c"]), float(ext_y["d"]), float(ext_y["value"]),
                                      sc.F / float(ext_y["c"]))
        grid = runs[runs["stage"] == "grid"] if len(runs) else runs
        ph.checks.update(roi_checks(sr, region, grid, xs, zs, sc.t_ramp))
    finally:
        ph.runs = sr.runs
        sr.close()
    return ph


def optimum_time_series(study, spec: PlanSpec, optimum: Mapping[str, float], t_eq: float,
                        t_ramp: float | None) -> dict:
    """The pullout at the optimum sampled every 0.01 s (y, v_y, F_pull) and, around the ramp's end, every
    0.5 ms (v_y, a_y): {"df", "zoom", "t_eq"}, or {"note"} when the FMU lacks these outputs."""
    params, stop = study.fmu_values(optimum), float(study.scenario.stop_time)
    inputs = dict(study.scenario.inputs) or None
    with runner_for(spec) as r:
        missing = [n for n in ("y", "v_y", "F_pull") if n not in r.variables]
        if missing:
            return {"note": f"No time-series figure: the FMU has no output {', '.join(missing)} (the figure "
                            f"plots the ScrewVertebra FMU's y, v_y and F_pull)."}
        df = r.run(params, stop, 0.01, ["y", "v_y", "F_pull"], inputs=inputs)
        zoom = None
        if t_ramp is not None and math.isfinite(t_eq) and t_eq < stop:
            t1 = min(stop, t_eq + max(0.02, 0.5 * (t_eq - t_ramp)))
            z = r.run(params, t1, 5e-4, ["v_y", "a_y"] if "a_y" in r.variables else ["v_y"], inputs=inputs)
            t0 = max(0.0, t_ramp - max(0.01, 0.5 * (t_eq - t_ramp)))
            zoom = z[z["time"] >= t0].reset_index(drop=True)
    return {"df": df, "zoom": zoom, "t_eq": t_eq}

