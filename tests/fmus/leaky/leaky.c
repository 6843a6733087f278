/* Leaky: a tiny FMI 2.0 co-simulation FMU that leaks memory and speaks non-ASCII (a test fixture of fmusa).
 *
 * Physics: a quasi-static spring, y = F / k, with y_peak = max |y| over the run.
 *
 * Every fmi2DoStep allocates `leak_mb` MB, touches every page of it and never frees it: a worker that
 * runs it again and again grows by leak_mb per step (tests/test_faults_pool.py recycles it).
 * With crash_above_mb > 0, fmi2DoStep aborts (SIGABRT) once the process has leaked more than that: a
 * run that works on a fresh worker and crashes a worn one, as an allocation failure does.
 * While fail_lo <= k <= fail_hi, fmi2DoStep logs a message in UTF-8 with non-ASCII letters and signs
 * ("Überlast bei k = ...: F ≥ k·Δy") and returns fmi2Error (tests/test_portability.py reads it back
 * under LC_ALL=C).
 *
 * Built by the tests with the FMI 2 headers from fmpy's c-code directory:
 *   gcc -shared -fPIC -O1 -I <fmpy>/c-code leaky.c -o Leaky.so
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "../common/cs_stubs.h"

#ifdef LEAKY_EXIT_ON_LOAD
#include <unistd.h>
/* built with -DLEAKY_EXIT_ON_LOAD: the process that loads the library exits at once (code 3), as a
   binary with a missing dependency or a broken static initialiser can */
__attribute__((constructor)) static void exit_on_load(void) { _exit(3); }
#endif

/* value references, as in modelDescription.xml */
enum { VR_K = 0, VR_F = 1, VR_LEAK_MB = 2, VR_FAIL_LO = 3, VR_FAIL_HI = 4, VR_Y = 5, VR_Y_PEAK = 6,
       VR_CRASH_ABOVE_MB = 7, N_REAL = 8 };
enum { VR_INT0 = 100, N_INT = 0 };

static const double REAL_START[N_REAL] = {1e6, 411.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0};

/* bytes this process has leaked, over every instance */
static double leaked_mb = 0.0;

typedef struct {
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    double r[N_REAL];
    int i[1];
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
    if (!instanceName) instanceName = "Leaky";
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
        if (vr[k] >= N_REAL || vr[k] == VR_Y || vr[k] == VR_Y_PEAK) {
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
    if (m->r[VR_LEAK_MB] > 0) {                   /* leaked on purpose: never freed */
        size_t n = (size_t)(m->r[VR_LEAK_MB] * 1024.0 * 1024.0);
        char *p = malloc(n);
        if (!p) {
            logmsg(m, fmi2Error, "logStatusError", "out of memory after leaking");
            return fmi2Error;
        }
        memset(p, 1, n);
        leaked_mb += m->r[VR_LEAK_MB];
    }
    if (m->r[VR_CRASH_ABOVE_MB] > 0 && leaked_mb > m->r[VR_CRASH_ABOVE_MB]) {
        abort();                                  /* as a C++ model does when an allocation fails */
    }
    if (k >= m->r[VR_FAIL_LO] && k <= m->r[VR_FAIL_HI]) {
        logmsg(m, fmi2Error, "logStatusError", "\xc3\x9c" "berlast bei k = %.17g: F \xe2\x89\xa5 k\xc2\xb7\xce\x94y", k);
        return fmi2Error;
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
