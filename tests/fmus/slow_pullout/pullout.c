/* A stand-in FMU for the search in rounds (issue 20): the paper's axial pullout in closed form, made slow.
 *
 * A vendor FMU (Simpack, Dymola, Amesim) costs seconds per run; this one sleeps ``sleep_s`` seconds of wall
 * time in every fmi2DoStep (sleeping needs no core, so 16 of them run at once on a 2-core machine) and then
 * returns the pullout of the screw on the massless spring-damper of the interface,
 *
 *     d y' + c y = F(t),   F(t) = F_max * min(t / t_ramp, 1),   y(0) = 0,
 *
 * in closed form (tau = d / c, A = F_max / (c t_ramp), the quasi-static ramp velocity):
 *
 *     ramp  (t <= t_ramp):  y = A (t - tau (1 - e^(-t/tau))),        v = A (1 - e^(-t/tau))
 *     hold  (s = t - t_ramp): y = y_s - (y_s - y_r) e^(-s/tau),     v = v_r e^(-s/tau),   y_s = F_max / c
 *
 * The screw's mass is left out (its natural period, ~0.1 ms, is far below the 10 s ramp). y and v never
 * decrease and fall, so max |y| = y(t), max |v| = v(min(t, t_ramp)); the means are the integrals over
 * [0, t] divided by t (mean |v| = y(t) / t). The ramp counts as motion; after it |a| = |v| / tau, so the
 * screw is at rest (|v| <= eps_v_eq and |a| <= eps_a_eq) from
 *
 *     t_eq = t_ramp + tau ln(v_r / min(eps_v_eq, eps_a_eq tau))      (t_ramp when that log is <= 0),
 *
 * reported once t >= t_eq, else -1 (as ScrewVertebra's t_eq). The variable names are ScrewVertebra's, so
 * studies/paper.yaml runs on it with `fmu:` pointing here. Co-Simulation only.
 *
 * Value references:
 *   0 c_y  1 d_y  2 F_max  3 t_ramp  4 eps_v_eq  5 eps_a_eq  6 sleep_s     parameters
 *   7 y_max  8 y_mean  9 v_y_max  10 v_y_mean  11 t_eq                      outputs
 */
#define _POSIX_C_SOURCE 200809L   /* nanosleep under -std=c99 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#ifdef _WIN32
#include <windows.h>
#else
#include <time.h>
#endif

#include "fmi2Functions.h"

#define GUID "{0d7c3e52-9b7a-4c61-8f0e-2a4b6c8d1e35}"
#define NVR 12
#define NPAR 7

enum { VR_c, VR_d, VR_F_max, VR_t_ramp, VR_eps_v, VR_eps_a, VR_sleep, VR_y_max, VR_y_mean, VR_v_max, VR_v_mean,
       VR_t_eq };

static const double START[NVR] = {823224.0, 488.0, 411.0, 10.0, 5e-8, 5e-9, 0.5, 0, 0, 0, 0, -1};

typedef struct {
    double r[NVR];
    double time;
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

static void pause_for(double s)
{
    if (!(s > 0)) return;
#ifdef _WIN32
    Sleep((DWORD)(s * 1e3 + 0.5));
#else
    struct timespec ts;
    ts.tv_sec = (time_t)s;
    ts.tv_nsec = (long)((s - (double)ts.tv_sec) * 1e9);
    while (nanosleep(&ts, &ts) != 0) {}
#endif
}

/* 1 - e^(-x/tau) and the ramp's integrals, exact also for tau -> 0 */
static double one_minus_exp(double x, double tau) { return tau > 0 ? -expm1(-x / tau) : 1.0; }

/* The closed form at time t: the monitors over [0, t]. */
static void outputs(Comp *c, double t)
{
    double cy = c->r[VR_c], d = c->r[VR_d], F = c->r[VR_F_max], tr = c->r[VR_t_ramp];
    double tau = d / cy, A = F / (cy * tr), ys = F / cy;
    double t1 = t < tr ? t : tr;                          /* end of the ramp piece in [0, t] */
    double y1 = A * (t1 - tau * one_minus_exp(t1, tau));
    double v1 = A * one_minus_exp(t1, tau);
    /* integral of y over the ramp piece: A (t1^2/2 - tau t1 + tau^2 (1 - e^(-t1/tau))) */
    double iy = A * (0.5 * t1 * t1 - tau * t1 + tau * tau * one_minus_exp(t1, tau));
    double y = y1;
    if (t > tr) {
        double s = t - tr, e = tau > 0 ? exp(-s / tau) : 0.0;
        y = ys - (ys - y1) * e;
        iy += ys * s - (ys - y1) * tau * one_minus_exp(s, tau);
    }
    c->r[VR_y_max] = y;
    c->r[VR_v_max] = v1;
    c->r[VR_y_mean] = t > 0 ? iy / t : 0.0;
    c->r[VR_v_mean] = t > 0 ? y / t : 0.0;
    double floor_v = c->r[VR_eps_v], floor_a = c->r[VR_eps_a] * tau;
    double lim = floor_v < floor_a ? floor_v : floor_a;
    double rest = tr;
    if (tau > 0 && v1 > lim) rest = tr + tau * log(v1 / lim);
    c->r[VR_t_eq] = (t >= tr && t >= rest) ? rest : -1.0;
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
    const char *nm = name ? name : "pullout";
    c->name = malloc(strlen(nm) + 1);
    if (!c->name) { free(c); return NULL; }
    strcpy(c->name, nm);
    (void)type;
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
    if (!(c->r[VR_c] > 0) || !(c->r[VR_d] >= 0) || !(c->r[VR_t_ramp] > 0)) {
        say(c, fmi2Error, "need c_y > 0, d_y >= 0 and t_ramp > 0, got %g, %g, %g", c->r[VR_c], c->r[VR_d],
            c->r[VR_t_ramp]);
        return fmi2Error;
    }
    outputs(c, c->time);
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    ((Comp *)comp)->initialised = 1;
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
        if (k >= NPAR) { say(c, fmi2Error, "fmi2SetReal: value reference %u cannot be set", k); return fmi2Error; }
        if (c->initialised) {
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

/* ------------------------------------------------------------------ Co-Simulation */
fmi2Status fmi2DoStep(fmi2Component comp, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior)
{
    Comp *c = comp;
    (void)noSetPrior;
    pause_for(c->r[VR_sleep]);      /* the cost of a vendor FMU's run, in wall time only */
    c->time = t + h;
    outputs(c, c->time);
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
