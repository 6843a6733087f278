/* Faulty: a damped oscillator under a constant load, exported the ways real tools get FMI 2.0 wrong
 * (a test fixture of fmusa; tests/faulty_fmu.py builds it and writes its modelDescription.xml).
 *
 * Physics: m x'' + d x' + k x = F (F a parameter, plus the input u), x(0) = x0, x'(0) = 0.
 * Outputs x, v and x_peak = max |x| over the run (at the internal steps).
 *
 * Co-simulation integrates with classical Runge-Kutta in internal steps of at most h_max, so that the
 * result is the closed form to ~1e-10; model exchange exposes (x, v) to the importer's solver.
 *
 * Each fault is a compile-time switch (-D...), one binary per fault, as an exporter bakes it in:
 *   FAULT_RESET_ZERO    fmi2Reset restores x0 = 0 instead of its start value 0.5 (Dymola 2022x)
 *   FAULT_RESET_ZEROS   after fmi2Reset every output reads 0 (20-sim 4.6)
 *   FAULT_RESET_ERROR   fmi2Reset returns fmi2Error (Amesim 15)
 *   FAULT_DROP_EARLY    fmi2SetupExperiment restores every parameter's start value: values set before it
 *                       are dropped (20-sim 4.6)
 *   FAULT_EULER         co-simulation steps with one explicit Euler step per communication step
 *                       (OpenModelica's CS export)
 *   WITH_STATE          canGetAndSetFMUstate: fmi2Get/Set/FreeFMUstate copy the instance
 *   LOG_TEXT            a string logged (status OK) by fmi2ExitInitializationMode
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

enum { VR_M = 0, VR_K = 1, VR_D = 2, VR_F = 3, VR_X0 = 4, VR_HMAX = 5, VR_U = 6,
       VR_X = 7, VR_V = 8, VR_XPEAK = 9, VR_K2 = 10, VR_DERV = 11, VR_TOL = 12, N_REAL = 13 };
/* VR_K2: the second variable named "k" of an ambiguous description (it changes nothing);
   VR_DERV: der(v), computed when read; VR_TOL: the tolerance fmi2SetupExperiment was given (-1: none) */

static const double REAL_START[N_REAL] = {1.0, 100.0, 2.0, 10.0, 0.5, 1e-3, 0.0, 0.5, 0.0, 0.5, 100.0, 0.0, -1.0};

typedef struct {
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    fmi2Type type;
    double r[N_REAL];
    double time;
    int zeros;          /* FAULT_RESET_ZEROS: outputs read 0 */
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

static void start_values(Model *m) {
    memcpy(m->r, REAL_START, sizeof m->r);
    m->time = 0.0;
}

static void initial_state(Model *m) {
    m->r[VR_X] = m->r[VR_X0];
    m->r[VR_V] = 0.0;
    m->r[VR_XPEAK] = fabs(m->r[VR_X]);
}

static void deriv(const Model *m, double x, double v, double *dx, double *dv) {
    *dx = v;
    *dv = (m->r[VR_F] + m->r[VR_U] - m->r[VR_K] * x - m->r[VR_D] * v) / m->r[VR_M];
}

static void rk4(Model *m, double h) {
    double x = m->r[VR_X], v = m->r[VR_V], k1x, k1v, k2x, k2v, k3x, k3v, k4x, k4v;
    deriv(m, x, v, &k1x, &k1v);
    deriv(m, x + 0.5 * h * k1x, v + 0.5 * h * k1v, &k2x, &k2v);
    deriv(m, x + 0.5 * h * k2x, v + 0.5 * h * k2v, &k3x, &k3v);
    deriv(m, x + h * k3x, v + h * k3v, &k4x, &k4v);
    m->r[VR_X] = x + h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x);
    m->r[VR_V] = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v);
}

/* ------------------------------------------------------------------ common functions */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t n, const fmi2String cats[]) {
    (void)c; (void)loggingOn; (void)n; (void)cats;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String guid,
                              fmi2String resourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    Model *m;
    (void)guid; (void)resourceLocation; (void)visible; (void)loggingOn;
    m = calloc(1, sizeof *m);
    if (!m) return NULL;
    if (!instanceName) instanceName = "Faulty";
    m->name = malloc(strlen(instanceName) + 1);
    if (!m->name) { free(m); return NULL; }
    strcpy(m->name, instanceName);
    m->logger = functions ? functions->logger : NULL;
    m->env = functions ? functions->componentEnvironment : NULL;
    m->type = fmuType;
    start_values(m);
    initial_state(m);
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
    Model *m = c;
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
#ifdef FAULT_DROP_EARLY
    memcpy(m->r, REAL_START, sizeof m->r);
#endif
    m->r[VR_TOL] = toleranceDefined ? tolerance : -1.0;
    m->time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Model *m = c;
    if (!(m->r[VR_M] > 0)) {
        logmsg(m, fmi2Error, "logStatusError", "m = %g must be positive", m->r[VR_M]);
        return fmi2Error;
    }
    initial_state(m);
#ifdef LOG_TEXT
    logmsg(m, fmi2OK, "logAll", "%s", LOG_TEXT);
#endif
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c) {
    Model *m = c;
#ifdef FAULT_RESET_ERROR
    logmsg(m, fmi2Error, "logStatusError", "fmi2Reset is not supported");
    return fmi2Error;
#else
    start_values(m);
#ifdef FAULT_RESET_ZERO
    m->r[VR_X0] = 0.0;
#endif
#ifdef FAULT_RESET_ZEROS
    m->zeros = 1;
#endif
    initial_state(m);
    return fmi2OK;
#endif
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Model *m = c;
    size_t i;
    for (i = 0; i < nvr; i++) {
        if (vr[i] >= N_REAL) return fmi2Error;
        if (vr[i] == VR_DERV) {
            double dx;
            deriv(m, m->r[VR_X], m->r[VR_V], &dx, &value[i]);
        } else {
            value[i] = m->r[vr[i]];
        }
        if (m->zeros && vr[i] >= VR_X && vr[i] != VR_TOL) value[i] = 0.0;
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    (void)c; (void)vr; (void)value;
    return nvr ? fmi2Error : fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    (void)c; (void)vr; (void)value;
    return nvr ? fmi2Error : fmi2OK;
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)c; (void)vr; (void)value;
    return nvr ? fmi2Error : fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Model *m = c;
    size_t i;
    for (i = 0; i < nvr; i++) {
        if (vr[i] >= N_REAL || vr[i] == VR_DERV) return fmi2Error;
        m->r[vr[i]] = value[i];
    }
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    (void)c; (void)vr; (void)value;
    return nvr ? fmi2Error : fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)c; (void)vr; (void)value;
    return nvr ? fmi2Error : fmi2OK;
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)c; (void)vr; (void)value;
    return nvr ? fmi2Error : fmi2OK;
}

/* ------------------------------------------------------------------ FMU state */
#ifdef WITH_STATE
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    Model *copy = malloc(sizeof *copy);
    if (!copy) return fmi2Error;
    memcpy(copy, c, sizeof *copy);
    *s = copy;
    return fmi2OK;
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) {
    Model *m = c, *saved = s;
    char *name = m->name;
    if (!saved) return fmi2Error;
    memcpy(m, saved, sizeof *m);
    m->name = name;
    return fmi2OK;
}
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)c;
    if (s && *s) { free(*s); *s = NULL; }
    return fmi2OK;
}
#else
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)c; (void)s; return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)c; (void)s; return fmi2Error; }
#endif
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)c; (void)s; (void)n; return fmi2Error;
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    (void)c; (void)s; (void)b; (void)n; return fmi2Error;
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s) {
    (void)c; (void)b; (void)n; (void)s; return fmi2Error;
}
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real du[],
                                        fmi2Real dz[]) {
    (void)c; (void)u; (void)nu; (void)z; (void)nz; (void)du; (void)dz; return fmi2Error;
}

/* ------------------------------------------------------------------ model exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *e) {
    (void)c;
    e->newDiscreteStatesNeeded = fmi2False;
    e->terminateSimulation = fmi2False;
    e->nominalsOfContinuousStatesChanged = fmi2False;
    e->valuesOfContinuousStatesChanged = fmi2False;
    e->nextEventTimeDefined = fmi2False;
    e->nextEventTime = 0.0;
    return fmi2OK;
}
fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean a, fmi2Boolean *b, fmi2Boolean *d) {
    Model *m = c;
    (void)a;
    if (fabs(m->r[VR_X]) > m->r[VR_XPEAK]) m->r[VR_XPEAK] = fabs(m->r[VR_X]);
    *b = fmi2False;
    *d = fmi2False;
    return fmi2OK;
}
fmi2Status fmi2SetTime(fmi2Component c, fmi2Real t) { ((Model *)c)->time = t; return fmi2OK; }
fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t n) {
    Model *m = c;
    if (n != 2) return fmi2Error;
    m->r[VR_X] = x[0];
    m->r[VR_V] = x[1];
    return fmi2OK;
}
fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t n) {
    Model *m = c;
    if (n != 2) return fmi2Error;
    deriv(m, m->r[VR_X], m->r[VR_V], &dx[0], &dx[1]);
    return fmi2OK;
}
fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t n) { (void)c; (void)z; return n ? fmi2Error : fmi2OK; }
fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t n) {
    Model *m = c;
    if (n != 2) return fmi2Error;
    x[0] = m->r[VR_X];
    x[1] = m->r[VR_V];
    return fmi2OK;
}
fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t n) {
    size_t i;
    (void)c;
    for (i = 0; i < n; i++) x[i] = 1.0;
    return fmi2OK;
}

/* ------------------------------------------------------------------ co-simulation */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)c; (void)vr; (void)nvr; (void)order; (void)value; return fmi2Error;
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)c; (void)vr; (void)nvr; (void)order; (void)value; return fmi2Error;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    Model *m = c;
    (void)noSetPrior;
    if (!(h > 0)) return fmi2Error;
#ifdef FAULT_EULER
    {
        double dx, dv;
        deriv(m, m->r[VR_X], m->r[VR_V], &dx, &dv);
        m->r[VR_X] += h * dx;
        m->r[VR_V] += h * dv;
        if (fabs(m->r[VR_X]) > m->r[VR_XPEAK]) m->r[VR_XPEAK] = fabs(m->r[VR_X]);
    }
#else
    {
        double hmax = m->r[VR_HMAX] > 0 ? m->r[VR_HMAX] : 1e-3;
        long n = (long)ceil(h / hmax - 1e-9), i;
        double hs;
        if (n < 1) n = 1;
        hs = h / (double)n;
        for (i = 0; i < n; i++) {
            rk4(m, hs);
            if (fabs(m->r[VR_X]) > m->r[VR_XPEAK]) m->r[VR_XPEAK] = fabs(m->r[VR_X]);
        }
    }
#endif
    m->time = t + h;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    Model *m = c;
    if (s == fmi2LastSuccessfulTime) { *v = m->time; return fmi2OK; }
    return fmi2Discard;
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
