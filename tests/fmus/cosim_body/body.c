/* A small FMI 2.0 FMU for the coupling tests: a body on a soft spring-damper, with the interface force as an input.
 *
 *     m x'' = f - k x - b x',   x(0) = x0, x'(0) = 0
 *
 * Outputs x and v = x'. One binary for the three kinds of export the coupling master meets:
 *   - Model Exchange: states (x, v), derivatives (v, a), no events;
 *   - Co-Simulation: fmi2DoStep integrates with RK4 on sub-steps of at most min(h, 0.02 / max(sqrt(k/m), b/m))
 *     with the input affine over the step (fmi2SetRealInputDerivatives);
 *   - with -DWITH_INDICATOR, one event indicator (the displacement x) for model exchange;
 *   - with -DWITH_GLOBAL, a flaw some exports have: a static counter of the instances the loaded library has
 *     made, which shifts the start x(0) = x0 + 1e-3 * (instances made before), so that a second instance of
 *     the same loaded binary does not start where the first did;
 *   - with -DWITH_STATE, fmi2GetFMUstate / fmi2SetFMUstate / fmi2FreeFMUstate (a copy of the instance);
 *     without it they fail, as the model description then says canGetAndSetFMUstate="false".
 * Value references: 0 m, 1 k, 2 b, 3 x0 (parameters), 4 f (input), 5 x, 6 v (outputs, states), 7 a (der(v)).
 * It shares no code with fmusa. */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include "fmi2Functions.h"

/* the parameters' start values (another export of the same source: -DSTART_M=... in tests/rotor_fmu.py) */
#ifndef START_M
#define START_M 1.0
#endif
#ifndef START_K
#define START_K 100.0
#endif
#ifndef START_B
#define START_B 1.0
#endif

typedef struct {
    double p[4];      /* m, k, b, x0 */
    double f, df, t_f;
    double t, x, v;
    fmi2CallbackLogger log;
    fmi2ComponentEnvironment env;
} Body;

#ifdef WITH_GLOBAL
static int instances_made = 0;
#define GLOBAL_SHIFT (1e-3 * (instances_made - 1))
#else
#define GLOBAL_SHIFT 0.0
#endif

static void rate(const Body *c, double t, double x, double v, double *dx, double *dv)
{
    double f = c->f + c->df * (t - c->t_f);
    *dx = v;
    *dv = (f - c->p[1] * x - c->p[2] * v) / c->p[0];
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }
fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cat[])
{ (void)c; (void)on; (void)n; (void)cat; return fmi2OK; }

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String res,
                              const fmi2CallbackFunctions *cb, fmi2Boolean vis, fmi2Boolean log)
{
    (void)name; (void)type; (void)guid; (void)res; (void)vis; (void)log;
    Body *c = calloc(1, sizeof(Body));
    if (!c) return NULL;
#ifdef WITH_GLOBAL
    instances_made++;
#endif
    c->p[0] = START_M; c->p[1] = START_K; c->p[2] = START_B; c->p[3] = 0.0;
    c->log = cb ? cb->logger : NULL;
    c->env = cb ? cb->componentEnvironment : NULL;
    return c;
}
void fmi2FreeInstance(fmi2Component c) { free(c); }
fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean a, fmi2Real b, fmi2Real t0, fmi2Boolean d, fmi2Real e)
{ (void)a; (void)b; (void)d; (void)e; ((Body *)c)->t = t0; return fmi2OK; }
fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    Body *c = comp;
    c->x = c->p[3] + GLOBAL_SHIFT;
    c->v = 0.0;
    c->t_f = c->t;
    return fmi2OK;
}
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { (void)c; return fmi2Error; }

fmi2Status fmi2GetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t n, fmi2Real value[])
{
    Body *c = comp;
    for (size_t i = 0; i < n; i++) {
        double dx, dv;
        switch (vr[i]) {
        case 0: case 1: case 2: case 3: value[i] = c->p[vr[i]]; break;
        case 4: value[i] = c->f; break;
        case 5: value[i] = c->x; break;
        case 6: value[i] = c->v; break;
        case 7: rate(c, c->t, c->x, c->v, &dx, &dv); value[i] = dv; break;
        default: return fmi2Error;
        }
    }
    return fmi2OK;
}
fmi2Status fmi2SetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t n, const fmi2Real value[])
{
    Body *c = comp;
    for (size_t i = 0; i < n; i++) {
        if (vr[i] <= 3) c->p[vr[i]] = value[i];
        else if (vr[i] == 4) { c->f = value[i]; c->t_f = c->t; }
        else return fmi2Error;
    }
    return fmi2OK;
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[])
{ (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[])
{ (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[])
{ (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[])
{ (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[])
{ (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[])
{ (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK; }

#ifdef WITH_STATE
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s)
{
    Body *copy = *s ? *s : malloc(sizeof(Body));
    if (!copy) return fmi2Error;
    memcpy(copy, c, sizeof(Body));
    *s = copy;
    return fmi2OK;
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { memcpy(c, s, sizeof(Body)); return fmi2OK; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; free(*s); *s = NULL; return fmi2OK; }
#else
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
#endif
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) { (void)c; (void)s; (void)n; return fmi2Error; }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n)
{ (void)c; (void)s; (void)b; (void)n; return fmi2Error; }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s)
{ (void)c; (void)s; (void)b; (void)n; return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real du[], fmi2Real dz[])
{ (void)c; (void)u; (void)nu; (void)z; (void)nz; (void)du; (void)dz; return fmi2Error; }

/* model exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *e)
{
    (void)c;
    memset(e, 0, sizeof(*e));
    return fmi2OK;
}
fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean n, fmi2Boolean *ev, fmi2Boolean *term)
{ (void)c; (void)n; *ev = fmi2False; *term = fmi2False; return fmi2OK; }
fmi2Status fmi2SetTime(fmi2Component c, fmi2Real t) { ((Body *)c)->t = t; ((Body *)c)->t_f = t; return fmi2OK; }
fmi2Status fmi2SetContinuousStates(fmi2Component comp, const fmi2Real x[], size_t n)
{ Body *c = comp; if (n != 2) return fmi2Error; c->x = x[0]; c->v = x[1]; return fmi2OK; }
fmi2Status fmi2GetDerivatives(fmi2Component comp, fmi2Real d[], size_t n)
{ Body *c = comp; if (n != 2) return fmi2Error; rate(c, c->t, c->x, c->v, &d[0], &d[1]); return fmi2OK; }
#ifdef WITH_INDICATOR
/* one event indicator, the displacement (a crossing of the rest position: no event action, only its location) */
fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t n)
{ if (n != 1) return fmi2Error; z[0] = ((Body *)c)->x; return fmi2OK; }
#else
fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t n) { (void)c; (void)z; return n ? fmi2Error : fmi2OK; }
#endif
fmi2Status fmi2GetContinuousStates(fmi2Component comp, fmi2Real x[], size_t n)
{ Body *c = comp; if (n != 2) return fmi2Error; x[0] = c->x; x[1] = c->v; return fmi2OK; }
fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t n)
{ (void)c; for (size_t i = 0; i < n; i++) x[i] = 1.0; return fmi2OK; }

/* co-simulation */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component comp, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    Body *c = comp;
    for (size_t i = 0; i < n; i++) {
        if (vr[i] != 4 || order[i] != 1) return fmi2Error;
        c->df = value[i];
    }
    return fmi2OK;
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer o[], fmi2Real v[])
{ (void)c; (void)vr; (void)o; (void)v; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2DoStep(fmi2Component comp, fmi2Real t0, fmi2Real h, fmi2Boolean noSet)
{
    Body *c = comp;
    (void)noSet;
    double w = fmax(sqrt(c->p[1] / c->p[0]), c->p[2] / c->p[0]);
    int n = (int)ceil(h * w / 0.02);
    if (n < 1) n = 1;
    double hs = h / n, t = t0;
    for (int i = 0; i < n; i++) {
        double k1x, k1v, k2x, k2v, k3x, k3v, k4x, k4v;
        rate(c, t, c->x, c->v, &k1x, &k1v);
        rate(c, t + hs / 2, c->x + hs / 2 * k1x, c->v + hs / 2 * k1v, &k2x, &k2v);
        rate(c, t + hs / 2, c->x + hs / 2 * k2x, c->v + hs / 2 * k2v, &k3x, &k3v);
        rate(c, t + hs, c->x + hs * k3x, c->v + hs * k3v, &k4x, &k4v);
        c->x += hs / 6 * (k1x + 2 * k2x + 2 * k3x + k4x);
        c->v += hs / 6 * (k1v + 2 * k2v + 2 * k3v + k4v);
        t += hs;
    }
    /* the input keeps its value at the step end */
    c->f += c->df * (t0 + h - c->t_f);
    c->t = t0 + h;
    c->t_f = c->t;
    return fmi2OK;
}
fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) { (void)c; (void)s; (void)v; return fmi2Error; }
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) { (void)c; (void)s; (void)v; return fmi2Error; }
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) { (void)c; (void)s; (void)v; return fmi2Error; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) { (void)c; (void)s; (void)v; return fmi2Error; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) { (void)c; (void)s; (void)v; return fmi2Error; }
