/* A small FMI 2.0 FMU for the tests: a mass on a spring-damper, pulled by a ramped force.
 *
 *     m y'' + d y' + c y = F(t) + F_ext,   F(t) = F_max * min(t / t_ramp, 1),   y(0) = y'(0) = 0
 *
 * It is not ScrewVertebra and shares no code with it. The binary implements both FMI 2.0 interfaces:
 *
 *   - Model Exchange: continuous states (y, v), derivatives (v, a), no event indicators, and one time
 *     event at t_ramp (the kink of the force), announced through fmi2NewDiscreteStates;
 *   - Co-Simulation: fmi2DoStep integrates with classical RK4 on sub-steps of at most h_cs (and stops
 *     at t_ramp exactly).
 *
 * Which interface a model description declares is up to the test (tests/fmus/me_spring/build.py).
 *
 * Value references:
 *   0 c        parameter, fixed         spring stiffness [N/m]
 *   1 d        parameter, fixed         damping [N.s/m]
 *   2 m        parameter, fixed         mass [kg]
 *   3 F_max    parameter, tunable       force after the ramp [N]
 *   4 t_ramp   parameter, fixed         ramp time [s]
 *   5 y_static calculatedParameter      F_max / c [m]
 *   6 y        output, state            displacement [m]
 *   7 v        output, state, der(y)    velocity [m/s]
 *   8 a        output, der(v)           acceleration [m/s2]
 *   9 F        output                   applied force F(t) + F_ext [N]
 *  10 F_ext    input                    extra constant force [N]
 *  11 h_cs     parameter, fixed         largest RK4 sub-step of fmi2DoStep [s]
 *  12 g        constant                 9.81 (for the "cannot be set" check)
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

#define GUID "{5b0d2a6e-3c1f-4f7e-9a51-0c5e1f2a7b3d}"
#define NVR 13

enum { VR_c, VR_d, VR_m, VR_F_max, VR_t_ramp, VR_y_static, VR_y, VR_v, VR_a, VR_F, VR_F_ext, VR_h_cs, VR_g };

static const double START[NVR] = {400.0, 20.0, 1.0, 10.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1e-4, 9.81};

typedef struct {
    double r[NVR];
    double time;
    fmi2Type type;
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    int initialised;
} Comp;

static void say(Comp *c, fmi2Status st, const char *fmt, ...)
{
    if (!c || !c->logger) return;
    char buf[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    c->logger(c->env, c->name, st, st >= fmi2Error ? "logStatusError" : "logAll", "%s", buf);
}

static double force(const Comp *c, double t)
{
    double ramp = c->r[VR_t_ramp] > 0 ? t / c->r[VR_t_ramp] : 1.0;
    if (ramp > 1.0) ramp = 1.0;
    if (ramp < 0.0) ramp = 0.0;
    return c->r[VR_F_max] * ramp + c->r[VR_F_ext];
}

static double accel(const Comp *c, double t, double y, double v)
{
    return (force(c, t) - c->r[VR_d] * v - c->r[VR_c] * y) / c->r[VR_m];
}

static void update(Comp *c)
{
    c->r[VR_y_static] = c->r[VR_c] != 0 ? c->r[VR_F_max] / c->r[VR_c] : INFINITY;
    c->r[VR_F] = force(c, c->time);
    c->r[VR_a] = accel(c, c->time, c->r[VR_y], c->r[VR_v]);
}

/* ------------------------------------------------------------------ common */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component comp, fmi2Boolean on, size_t n, const fmi2String cat[])
{
    (void)comp; (void)on; (void)n; (void)cat;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *f, fmi2Boolean visible, fmi2Boolean logging)
{
    (void)resources; (void)visible; (void)logging;
    if (!guid || strcmp(guid, GUID) != 0) {
        if (f && f->logger) f->logger(f->componentEnvironment, name, fmi2Error, "logStatusError",
                                      "wrong GUID %s", guid ? guid : "NULL");
        return NULL;
    }
    Comp *c = calloc(1, sizeof(Comp));
    if (!c) return NULL;
    const char *nm = name ? name : "spring";
    c->name = malloc(strlen(nm) + 1);
    if (!c->name) { free(c); return NULL; }
    strcpy(c->name, nm);
    c->type = type;
    c->logger = f ? f->logger : NULL;
    c->env = f ? f->componentEnvironment : NULL;
    memcpy(c->r, START, sizeof START);
    return c;
}

void fmi2FreeInstance(fmi2Component comp)
{
    Comp *c = comp;
    if (!c) return;
    free(c->name);
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component comp, fmi2Boolean tolDef, fmi2Real tol, fmi2Real start,
                               fmi2Boolean stopDef, fmi2Real stop)
{
    Comp *c = comp;
    (void)tolDef; (void)tol; (void)stopDef; (void)stop;
    c->time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component comp)
{
    Comp *c = comp;
    if (!(c->r[VR_m] > 0)) {
        say(c, fmi2Error, "m must be > 0, got %g", c->r[VR_m]);
        return fmi2Error;
    }
    if (!(c->r[VR_t_ramp] >= 0) || !(c->r[VR_h_cs] > 0)) {
        say(c, fmi2Error, "t_ramp must be >= 0 and h_cs > 0");
        return fmi2Error;
    }
    c->r[VR_y] = 0.0;
    c->r[VR_v] = 0.0;
    update(c);
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    Comp *c = comp;
    update(c);
    c->initialised = 1;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component comp) { (void)comp; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component comp)
{
    Comp *c = comp;
    memcpy(c->r, START, sizeof START);
    c->time = 0.0;
    c->initialised = 0;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t n, fmi2Real value[])
{
    Comp *c = comp;
    update(c);
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= NVR) { say(c, fmi2Error, "fmi2GetReal: bad value reference %u", vr[i]); return fmi2Error; }
        value[i] = c->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t n, const fmi2Real value[])
{
    Comp *c = comp;
    for (size_t i = 0; i < n; i++) {
        fmi2ValueReference k = vr[i];
        int settable = k <= VR_t_ramp || k == VR_F_ext || k == VR_h_cs;
        if (!settable) { say(c, fmi2Error, "fmi2SetReal: value reference %u cannot be set", k); return fmi2Error; }
        if (c->initialised && k != VR_F_ext && k != VR_F_max) {
            say(c, fmi2Error, "fmi2SetReal: fixed parameter %u set after initialisation", k);
            return fmi2Error;
        }
        c->r[k] = value[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[])
{ (void)vr; (void)v; if (n) { say(c, fmi2Error, "no Integer variables"); return fmi2Error; } return fmi2OK; }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[])
{ (void)vr; (void)v; if (n) { say(c, fmi2Error, "no Boolean variables"); return fmi2Error; } return fmi2OK; }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[])
{ (void)vr; (void)v; if (n) { say(c, fmi2Error, "no String variables"); return fmi2Error; } return fmi2OK; }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[])
{ (void)vr; (void)v; if (n) { say(c, fmi2Error, "no Integer variables"); return fmi2Error; } return fmi2OK; }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[])
{ (void)vr; (void)v; if (n) { say(c, fmi2Error, "no Boolean variables"); return fmi2Error; } return fmi2OK; }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[])
{ (void)vr; (void)v; if (n) { say(c, fmi2Error, "no String variables"); return fmi2Error; } return fmi2OK; }

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n)
{ (void)c; (void)s; (void)n; return fmi2Error; }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n)
{ (void)c; (void)s; (void)b; (void)n; return fmi2Error; }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s)
{ (void)c; (void)s; (void)b; (void)n; return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dv[], fmi2Real dz[])
{ (void)c; (void)u; (void)nu; (void)z; (void)nz; (void)dv; (void)dz; return fmi2Error; }

/* ------------------------------------------------------------------ Model Exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2NewDiscreteStates(fmi2Component comp, fmi2EventInfo *info)
{
    Comp *c = comp;
    double tr = c->r[VR_t_ramp];
    info->newDiscreteStatesNeeded = fmi2False;
    info->terminateSimulation = fmi2False;
    info->nominalsOfContinuousStatesChanged = fmi2False;
    info->valuesOfContinuousStatesChanged = fmi2False;
    info->nextEventTimeDefined = c->time < tr - 1e-12 * (1.0 + fabs(tr)) ? fmi2True : fmi2False;
    info->nextEventTime = tr;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation)
{
    (void)c; (void)noSetFMUStatePriorToCurrentPoint;
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component comp, fmi2Real time) { ((Comp *)comp)->time = time; return fmi2OK; }

fmi2Status fmi2SetContinuousStates(fmi2Component comp, const fmi2Real x[], size_t nx)
{
    Comp *c = comp;
    if (nx != 2) { say(c, fmi2Error, "fmi2SetContinuousStates: nx = %zu, expected 2", nx); return fmi2Error; }
    c->r[VR_y] = x[0];
    c->r[VR_v] = x[1];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component comp, fmi2Real dx[], size_t nx)
{
    Comp *c = comp;
    if (nx != 2) { say(c, fmi2Error, "fmi2GetDerivatives: nx = %zu, expected 2", nx); return fmi2Error; }
    dx[0] = c->r[VR_v];
    dx[1] = accel(c, c->time, c->r[VR_y], c->r[VR_v]);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t nz)
{ (void)c; (void)z; return nz == 0 ? fmi2OK : fmi2Error; }

fmi2Status fmi2GetContinuousStates(fmi2Component comp, fmi2Real x[], size_t nx)
{
    Comp *c = comp;
    if (nx != 2) return fmi2Error;
    x[0] = c->r[VR_y];
    x[1] = c->r[VR_v];
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t nx)
{
    (void)c;
    for (size_t i = 0; i < nx; i++) x[i] = 1.0;
    return fmi2OK;
}

/* ------------------------------------------------------------------ Co-Simulation */
static void rk4(Comp *c, double t, double h)
{
    double y = c->r[VR_y], v = c->r[VR_v];
    double k1y = v, k1v = accel(c, t, y, v);
    double k2y = v + 0.5 * h * k1v, k2v = accel(c, t + 0.5 * h, y + 0.5 * h * k1y, v + 0.5 * h * k1v);
    double k3y = v + 0.5 * h * k2v, k3v = accel(c, t + 0.5 * h, y + 0.5 * h * k2y, v + 0.5 * h * k2v);
    double k4y = v + h * k3v, k4v = accel(c, t + h, y + h * k3y, v + h * k3v);
    c->r[VR_y] = y + h / 6.0 * (k1y + 2 * k2y + 2 * k3y + k4y);
    c->r[VR_v] = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v);
}

static void advance(Comp *c, double t0, double t1)
{
    double span = t1 - t0;
    if (span <= 0) return;
    int n = (int)ceil(span / c->r[VR_h_cs] - 1e-9);
    if (n < 1) n = 1;
    double h = span / n;
    for (int i = 0; i < n; i++) rk4(c, t0 + i * h, h);
}

fmi2Status fmi2DoStep(fmi2Component comp, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior)
{
    Comp *c = comp;
    (void)noSetPrior;
    double t_end = t + h, tr = c->r[VR_t_ramp];
    if (t < tr && t_end > tr) {   /* integrate the two smooth pieces separately */
        advance(c, t, tr);
        advance(c, tr, t_end);
    } else {
        advance(c, t, t_end);
    }
    c->time = t_end;
    update(c);
    if (!isfinite(c->r[VR_y])) { say(c, fmi2Error, "non-finite y at t = %g", t_end); return fmi2Error; }
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real value[])
{ (void)c; (void)vr; (void)n; (void)order; (void)value; return fmi2Error; }
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer order[], fmi2Real value[])
{ (void)c; (void)vr; (void)n; (void)order; (void)value; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v)
{ (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v)
{ (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v)
{ (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v)
{ (void)c; (void)s; (void)v; return fmi2Discard; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v)
{ (void)c; (void)s; (void)v; return fmi2Discard; }
