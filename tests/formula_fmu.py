"""Small co-simulation FMUs whose outputs are closed forms of their parameters and time, built with gcc.

``build_formula_fmu(dest, "Peak", {"p": 1.0}, {"y": "p * exp(-pow((t - 0.505) / 0.002, 2))"})`` writes
``dest/Peak.fmu``: a C FMU (FMI 2.0, co-simulation, linux64) with the Real parameters given (name -> start)
and outputs computed at every communication point from C expressions of the parameters and ``t``.
``refuse`` is a C condition on the parameters under which fmi2ExitInitializationMode returns fmi2Error
(an FMU that refuses a value, such as a stiffness of 0), with ``refuse_message`` logged. Every value an
output takes is known in closed form, so a test can hold fmusa's numbers to it. Parameters may not be named
``m`` or ``t`` (the C code's own names).
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import fmpy
import pytest

FMI_HEADERS = Path(fmpy.__file__).resolve().parent / "c-code"

_C = r"""
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "fmi2Functions.h"

#define NP %(np)d
#define NO %(no)d
static const double START[NP > 0 ? NP : 1] = {%(starts)s};

typedef struct { double p[NP > 0 ? NP : 1]; double y[NO]; double t; fmi2CallbackLogger logger;
                 fmi2ComponentEnvironment env; fmi2String name; } Model;

static void outputs(Model *m) {
    double t = m->t;
    %(unpack)s
    %(assign)s
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }
fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[]) {
    (void)c; (void)on; (void)n; (void)cats; return fmi2OK; }
fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String res,
                              const fmi2CallbackFunctions *f, fmi2Boolean visible, fmi2Boolean logging) {
    (void)guid; (void)res; (void)visible; (void)logging;
    if (type != fmi2CoSimulation) return NULL;
    Model *m = calloc(1, sizeof *m);
    if (!m) return NULL;
    memcpy(m->p, START, sizeof m->p);
    m->logger = f->logger; m->env = f->componentEnvironment; m->name = name;
    return m;
}
void fmi2FreeInstance(fmi2Component c) { free(c); }
fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean a, fmi2Real b, fmi2Real t0, fmi2Boolean d,
                               fmi2Real e) { (void)a; (void)b; (void)d; (void)e; ((Model *)c)->t = t0;
    return fmi2OK; }
fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component comp_) {
    Model *m = comp_;
    %(unpack)s
    if (%(refuse)s) {
        if (m->logger) m->logger(m->env, m->name, fmi2Error, "logStatusError", "%(refuse_message)s");
        return fmi2Error;
    }
    outputs(m);
    return fmi2OK;
}
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { Model *m = c; memcpy(m->p, START, sizeof m->p); m->t = 0;
    return fmi2OK; }
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    Model *m = c;
    for (size_t k = 0; k < n; k++) {
        if (vr[k] < NP) v[k] = m->p[vr[k]];
        else if (vr[k] < NP + NO) v[k] = m->y[vr[k] - NP];
        else return fmi2Error;
    }
    return fmi2OK;
}
fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Real v[]) {
    Model *m = c;
    for (size_t k = 0; k < n; k++) { if (vr[k] >= NP) return fmi2Error; m->p[vr[k]] = v[k]; }
    return fmi2OK;
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)c; (void)s; (void)n; return fmi2Error; }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    (void)c; (void)s; (void)b; (void)n; return fmi2Error; }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s) {
    (void)c; (void)b; (void)n; (void)s; return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
    const fmi2ValueReference z[], size_t nz, const fmi2Real dv[], fmi2Real dz[]) {
    (void)c; (void)u; (void)nu; (void)z; (void)nz; (void)dv; (void)dz; return fmi2Error; }
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
    const fmi2Integer o[], const fmi2Real v[]) { (void)c; (void)vr; (void)n; (void)o; (void)v; return fmi2Error; }
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
    const fmi2Integer o[], fmi2Real v[]) { (void)c; (void)vr; (void)n; (void)o; (void)v; return fmi2Error; }
fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noPrior) {
    Model *m = c; (void)noPrior;
    m->t = t + h;
    outputs(m);
    return fmi2OK;
}
fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) {
    (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) {
    (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) {
    (void)c; (void)s; (void)v; return fmi2Discard; }
"""


def _description(name: str, params: dict[str, float], outputs: list[str], stop: float) -> str:
    rows = [f'<ScalarVariable name="{p}" valueReference="{i}" causality="parameter" variability="tunable" '
            f'initial="exact"><Real start="{v!r}"/></ScalarVariable>' for i, (p, v) in enumerate(params.items())]
    rows += [f'<ScalarVariable name="{o}" valueReference="{len(params) + j}" causality="output" '
             f'variability="continuous" initial="calculated"><Real/></ScalarVariable>'
             for j, o in enumerate(outputs)]
    idx = "".join(f'<Unknown index="{len(params) + j + 1}"/>' for j in range(len(outputs)))
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="{name}" guid="{{formula-{name}}}" generationTool="tests/formula_fmu.py"
  variableNamingConvention="flat" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="{name}" canHandleVariableCommunicationStepSize="true"
    canGetAndSetFMUstate="false"/>
  <LogCategories><Category name="logStatusError"/></LogCategories>
  <DefaultExperiment startTime="0" stopTime="{stop!r}"/>
  <ModelVariables>
{chr(10).join(rows)}
  </ModelVariables>
  <ModelStructure><Outputs>{idx}</Outputs><InitialUnknowns>{idx}</InitialUnknowns></ModelStructure>
</fmiModelDescription>
"""


def build_formula_fmu(dest: Path, name: str, params: dict[str, float], outputs: dict[str, str], *,
                      refuse: str = "0", refuse_message: str = "parameter value refused",
                      stop: float = 1.0) -> Path:
    """``dest``/<name>.fmu: outputs = the C expressions ``outputs`` of the parameters and ``t``."""
    if not sys.platform.startswith("linux") or shutil.which("gcc") is None:
        pytest.skip("the formula test FMUs are built with gcc as linux64 binaries")
    tree = dest / f"{name}.tree"
    so = tree / "binaries" / fmpy.platform / f"{name}{fmpy.sharedLibraryExtension}"
    so.parent.mkdir(parents=True, exist_ok=True)
    names = list(params)
    unpack = " ".join(f"double {p} = m->p[{i}]; (void){p};" for i, p in enumerate(names))
    assign = " ".join(f"m->y[{j}] = {expr};" for j, expr in enumerate(outputs.values()))
    src = tree.parent / f"{name}.c"
    src.write_text(_C % {"np": len(names), "no": len(outputs), "unpack": unpack, "assign": assign,
                         "starts": ", ".join(repr(float(v)) for v in params.values()) or "0",
                         "refuse": refuse, "refuse_message": refuse_message}, encoding="utf-8")
    cmd = ["gcc", "-std=c99", "-O1", "-shared", "-fPIC", "-I", str(FMI_HEADERS), str(src), "-o", str(so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"building {name} failed:\n{proc.stderr}")
    (tree / "modelDescription.xml").write_text(_description(name, params, list(outputs), stop), encoding="utf-8")
    fmu = dest / f"{name}.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    shutil.rmtree(tree)
    return fmu
