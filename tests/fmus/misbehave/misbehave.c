/* Misbehave: a tiny FMI 2.0 co-simulation FMU that misbehaves on purpose (a test fixture of fmusa).
 *
 * Physics: a quasi-static spring, y = F / k, with y_peak = max |y| over the run.
 *
 * While `fault` != 0 and fault_lo <= k <= fault_hi, every fmi2DoStep misbehaves according to
 * `fault_kind`:
 *   1  segfault (writes through a NULL pointer)
 *   2  hangs (loops for ever)
 *   3  returns fmi2OK but sets the outputs to NaN
 *   4  logs "deliberate failure at k = ..." and returns fmi2Error
 * Any other fault_kind, or k outside the band, behaves.
 *
 * Built by tests/test_misbehaving_fmu.py with the FMI 2 headers from fmpy's c-code directory:
 *   gcc -shared -fPIC -O1 -I <fmpy>/c-code misbehave.c -o Misbehave.so
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "../common/cs_stubs.h"

/* value references, as in modelDescription.xml */
enum { VR_K = 0, VR_F = 1, VR_FAULT = 2, VR_FAULT_LO = 3, VR_FAULT_HI = 4, VR_Y = 5, VR_Y_PEAK = 6,
       N_REAL = 7 };
enum { VR_INT0 = 100, VR_FAULT_KIND = 100, N_INT = 1 };   /* Integers: 100, 101, ... */

static const double REAL_START[N_REAL] = {1e6, 411.0, 0.0, 0.0, 0.0, 0.0, 0.0};
static const int INT_START[N_INT] = {0};

typedef struct {
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    double r[N_REAL];
    int i[N_INT];
    double time;
} Model;

static void logmsg(Model *m, fmi2Status status, const char *category, const char *fmt, ...) {
    char buf[512];
    va_list ap;
    if (!m || !m->logger) return;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    m->logger(m->env, m->name, status, category, "%s", buf);
}

static void reset_values(Model *m) {
    memcpy(m->r, REAL_START, sizeof m->r);
    memcpy(m->i, INT_START, sizeof m->i);
    m->time = 0.0;
}

static void compute(Model *m) {
    m->r[VR_Y] = m->r[VR_F] / m->r[VR_K];
    if (fabs(m->r[VR_Y]) > m->r[VR_Y_PEAK]) m->r[VR_Y_PEAK] = fabs(m->r[VR_Y]);
}

/* ------------------------------------------------------------------ common functions */

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t n, const fmi2String cats[]) {
    (void)c; (void)loggingOn; (void)n; (void)cats;
    return fmi2OK;   /* errors are always logged; there is nothing else to log */
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String guid,
                              fmi2String resourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    Model *m;
    (void)guid; (void)resourceLocation; (void)visible; (void)loggingOn;
    if (fmuType != fmi2CoSimulation) return NULL;
    m = calloc(1, sizeof *m);
    if (!m) return NULL;
    if (!instanceName) instanceName = "Misbehave";
    m->name = malloc(strlen(instanceName) + 1);
    if (!m->name) { free(m); return NULL; }
    strcpy(m->name, instanceName);
    m->logger = functions ? functions->logger : NULL;
    m->env = functions ? functions->componentEnvironment : NULL;
    reset_values(m);
    return m;
}

void fmi2FreeInstance(fmi2Component c) {
    Model *m = c;
    if (!m) return;
    free(m->name);
    free(m);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    ((Model *)c)->time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Model *m = c;
    if (!(m->r[VR_K] > 0)) {
        logmsg(m, fmi2Error, "logStatusError", "k must be > 0, got %g", m->r[VR_K]);
        return fmi2Error;
    }
    m->r[VR_Y_PEAK] = 0.0;
    compute(m);
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c) { reset_values((Model *)c); return fmi2OK; }

/* ------------------------------------------------------------------ getters and setters */
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Model *m = c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] >= N_REAL) return fmi2Error;
        value[k] = m->r[vr[k]];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    Model *m = c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] < VR_INT0 || vr[k] >= VR_INT0 + N_INT) return fmi2Error;
        value[k] = m->i[vr[k] - VR_INT0];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Model *m = c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] > VR_FAULT_HI) {
            logmsg(m, fmi2Error, "logStatusError", "variable %u cannot be set", (unsigned)vr[k]);
            return fmi2Error;
        }
        m->r[vr[k]] = value[k];
    }
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    Model *m = c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] < VR_INT0 || vr[k] >= VR_INT0 + N_INT) return fmi2Error;
        m->i[vr[k] - VR_INT0] = value[k];
    }
    return fmi2OK;
}

/* ------------------------------------------------------------------ co-simulation */

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    Model *m = c;
    double k = m->r[VR_K];
    (void)noSetPrior;
    if (m->r[VR_FAULT] != 0.0 && k >= m->r[VR_FAULT_LO] && k <= m->r[VR_FAULT_HI]) {
        switch (m->i[VR_FAULT_KIND - VR_INT0]) {
        case 1: {                                   /* segfault */
            volatile int *volatile p = NULL;   /* volatile store: the compiler may not drop it */
            *p = 42;
            break;
        }
        case 2: {                                   /* hang */
            volatile int spin = 1;
            while (spin) { }
            break;
        }
        case 3:                                     /* NaN outputs, status OK */
            m->r[VR_Y] = NAN;
            m->r[VR_Y_PEAK] = NAN;
            m->time = t + h;
            return fmi2OK;
        case 4:                                     /* an error the FMU reports */
            logmsg(m, fmi2Error, "logStatusError", "deliberate failure at k = %.17g", k);
            return fmi2Error;
        default:
            break;
        }
    }
    m->time = t + h;
    compute(m);
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    Model *m = c;
    if (s == fmi2LastSuccessfulTime) { *v = m->time; return fmi2OK; }
    return fmi2Discard;
}
