/* TestFunc: an FMI 2.0 co-simulation FMU of test functions with known Sobol indices (a test fixture of
 * fmusa): the inputs x1 ... x8 are parameters, the outputs are computed from them.
 *
 *   ishigami = sin(x1) + A sin(x2)^2 + B x3^4 sin(x1)            (A = 7, B = 0.1; x_i uniform on [-pi, pi])
 *   gfun     = prod_i (|4 x_i - 2| + a_i) / (1 + a_i), i = 1..8   (Sobol's G; x_i uniform on [0, 1])
 *   linear   = x1 + 2 x2 + 3 x3                                   (additive: S1 = ST = c_i^2 var_i / var)
 *
 * Built by the tests with the FMI 2 headers from fmpy's c-code directory:
 *   gcc -shared -fPIC -O1 -I <fmpy>/c-code testfunc.c -o TestFunc.so -lm
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "../common/cs_stubs.h"

#define NX 8
/* value references, as in the model description the tests write: x1..x8 = 0..7, a1..a8 = 8..15, A = 16,
   B = 17, outputs ishigami = 18, gfun = 19, linear = 20 */
enum { VR_X = 0, VR_A = 8, VR_ISH_A = 16, VR_ISH_B = 17, VR_ISHIGAMI = 18, VR_GFUN = 19, VR_LINEAR = 20, N_REAL = 21 };

typedef struct {
    double r[N_REAL];
    double time;
} Model;

static void reset_values(Model *m) {
    memset(m->r, 0, sizeof m->r);
    m->r[VR_ISH_A] = 7.0;
    m->r[VR_ISH_B] = 0.1;
    m->time = 0.0;
}

static void compute(Model *m) {
    const double *x = m->r + VR_X, *a = m->r + VR_A;
    double g = 1.0;
    m->r[VR_ISHIGAMI] = sin(x[0]) + m->r[VR_ISH_A] * sin(x[1]) * sin(x[1])
                        + m->r[VR_ISH_B] * pow(x[2], 4) * sin(x[0]);
    for (int i = 0; i < NX; i++) g *= (fabs(4.0 * x[i] - 2.0) + a[i]) / (1.0 + a[i]);
    m->r[VR_GFUN] = g;
    m->r[VR_LINEAR] = x[0] + 2.0 * x[1] + 3.0 * x[2];
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[]) {
    (void)c; (void)on; (void)n; (void)cats; return fmi2OK;
}
fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String res,
                              const fmi2CallbackFunctions *f, fmi2Boolean visible, fmi2Boolean logging) {
    Model *m;
    (void)name; (void)guid; (void)res; (void)f; (void)visible; (void)logging;
    if (type != fmi2CoSimulation) return NULL;
    m = calloc(1, sizeof *m);
    if (m) reset_values(m);
    return m;
}
void fmi2FreeInstance(fmi2Component c) { free(c); }
fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean td, fmi2Real tol, fmi2Real t0, fmi2Boolean sd,
                               fmi2Real t1) {
    (void)td; (void)tol; (void)sd; (void)t1; ((Model *)c)->time = t0; return fmi2OK;
}
fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) { compute((Model *)c); return fmi2OK; }
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { reset_values((Model *)c); return fmi2OK; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Model *m = c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] >= N_REAL) return fmi2Error;
        value[k] = m->r[vr[k]];
    }
    return fmi2OK;
}
fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Model *m = c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] >= VR_ISHIGAMI) return fmi2Error;
        m->r[vr[k]] = value[k];
    }
    return fmi2OK;
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    Model *m = c;
    (void)noSetPrior;
    m->time = t + h;
    compute(m);
    return fmi2OK;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    if (s == fmi2LastSuccessfulTime) { *v = ((Model *)c)->time; return fmi2OK; }
    return fmi2Discard;
}
