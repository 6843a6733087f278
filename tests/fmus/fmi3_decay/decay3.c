/* Decay3: a small FMI 3.0 FMU for the tests (co-simulation and model exchange in one binary).
 *
 *     x_i' = u - k_i x_i,   x_i(0) = x0_i   (i = 1, 2)      z = s w x   (w a 2x2 matrix)
 *
 * with s = (negate ? -1 : 1) * 10^scale_exp (a Boolean and an Int32 parameter), and n_steps (an Int32
 * output) counting the calls of fmi3DoStep since the reset. From t = t_terminate on, fmi3DoStep asks the
 * importer to end the simulation (terminateSimulation).
 *
 * so x_i(t) = u/k_i + (x0_i - u/k_i) exp(-k_i t): the closed form tests/test_fmi3.py checks.
 * Arrays: parameters k[2], x0[2] and w[2,2] (row-major), outputs x[2] (the states) and z[2]; one scalar
 * input u. fmi3DoStep advances each state with the exact exponential of the step (so a co-simulation run
 * is the closed form to rounding); model exchange gives the derivatives to fmpy's solver.
 *
 * Value references (as in tests/fmus/fmi3_decay/modelDescription.xml):
 *   0 time   1 k[2]   2 x0[2]   3 w[2,2]   4 u   5 x[2]   6 der(x)[2]   7 z[2]
 *   8 negate (Boolean)   9 scale_exp (Int32)   10 n_steps (Int32)   11 t_terminate
 * Built by tests/test_fmi3.py with gcc and the FMI 3 headers of fmpy's c-code directory. Functions this
 * model does not support return fmi3Error (every function fmpy binds must exist).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"

enum { VR_TIME = 0, VR_K = 1, VR_X0 = 2, VR_W = 3, VR_U = 4, VR_X = 5, VR_DX = 6, VR_Z = 7, VR_NEGATE = 8,
       VR_SCALE_EXP = 9, VR_N_STEPS = 10, VR_T_TERMINATE = 11 };

typedef struct {
    double k[2], x0[2], w[4], u, x[2];
    double time, t_terminate;
    fmi3Boolean negate;
    fmi3Int32 scale_exp, n_steps;
    int initialised;
    fmi3InstanceEnvironment env;
    fmi3LogMessageCallback log;
} Model;

static void defaults(Model *m) {
    m->k[0] = 1.0; m->k[1] = 2.0;
    m->x0[0] = 1.0; m->x0[1] = -0.5;
    m->w[0] = 1.0; m->w[1] = 0.0; m->w[2] = 0.0; m->w[3] = 1.0;
    m->u = 0.0;
    m->x[0] = m->x0[0]; m->x[1] = m->x0[1];
    m->time = 0.0;
    m->t_terminate = 1e300;
    m->negate = fmi3False;
    m->scale_exp = 0;
    m->n_steps = 0;
    m->initialised = 0;
}

static double output_scale(const Model *m) {
    return (m->negate ? -1.0 : 1.0) * pow(10.0, (double)m->scale_exp);
}

static void fail(Model *m, const char *what) {
    if (m && m->log) m->log(m->env, fmi3Error, "logStatusError", what);
}

/* the values of variable vr (n of them) at dst; the number written, or -1 for an unknown vr */
static int get_values(Model *m, fmi3ValueReference vr, double *dst, size_t room) {
    double v[4];
    int n = 0, i;
    switch (vr) {
    case VR_TIME: v[0] = m->time; n = 1; break;
    case VR_K: v[0] = m->k[0]; v[1] = m->k[1]; n = 2; break;
    case VR_X0: v[0] = m->x0[0]; v[1] = m->x0[1]; n = 2; break;
    case VR_W: memcpy(v, m->w, sizeof m->w); n = 4; break;
    case VR_U: v[0] = m->u; n = 1; break;
    case VR_T_TERMINATE: v[0] = m->t_terminate; n = 1; break;
    case VR_X: v[0] = m->x[0]; v[1] = m->x[1]; n = 2; break;
    case VR_DX: v[0] = m->u - m->k[0] * m->x[0]; v[1] = m->u - m->k[1] * m->x[1]; n = 2; break;
    case VR_Z:
        v[0] = output_scale(m) * (m->w[0] * m->x[0] + m->w[1] * m->x[1]);
        v[1] = output_scale(m) * (m->w[2] * m->x[0] + m->w[3] * m->x[1]);
        n = 2; break;
    default: return -1;
    }
    if ((size_t)n > room) return -1;
    for (i = 0; i < n; i++) dst[i] = v[i];
    return n;
}

static int set_values(Model *m, fmi3ValueReference vr, const double *src, size_t room) {
    switch (vr) {
    case VR_K: if (room < 2) return -1; m->k[0] = src[0]; m->k[1] = src[1]; return 2;
    case VR_X0: if (room < 2) return -1; m->x0[0] = src[0]; m->x0[1] = src[1]; return 2;
    case VR_W: if (room < 4) return -1; memcpy(m->w, src, sizeof m->w); return 4;
    case VR_U: if (room < 1) return -1; m->u = src[0]; return 1;
    case VR_T_TERMINATE: if (room < 1) return -1; m->t_terminate = src[0]; return 1;
    default: return -1;
    }
}

/* ------------------------------------------------------------------ common functions */
const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    (void)instance; (void)loggingOn; (void)nCategories; (void)categories;
    return fmi3OK;
}

static Model *make(fmi3InstanceEnvironment env, fmi3LogMessageCallback log) {
    Model *m = calloc(1, sizeof *m);
    if (!m) return NULL;
    defaults(m);
    m->env = env;
    m->log = log;
    return m;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    return make(instanceEnvironment, logMessage);
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)eventModeUsed; (void)earlyReturnAllowed; (void)requiredIntermediateVariables;
    (void)nRequiredIntermediateVariables; (void)intermediateUpdate;
    return make(instanceEnvironment, logMessage);
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible,
                                               fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage,
                                               fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)instanceEnvironment; (void)logMessage; (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    return NULL;
}

void fmi3FreeInstance(fmi3Instance instance) { free(instance); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    Model *m = instance;
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    m->time = startTime;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    Model *m = instance;
    if (!(m->k[0] > 0 && m->k[1] > 0)) {
        fail(m, "k[1] and k[2] must be positive");
        return fmi3Error;
    }
    m->x[0] = m->x0[0];
    m->x[1] = m->x0[1];
    m->initialised = 1;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance) { (void)instance; return fmi3OK; }
fmi3Status fmi3Terminate(fmi3Instance instance) { (void)instance; return fmi3OK; }
fmi3Status fmi3Reset(fmi3Instance instance) {
    Model *m = instance;
    fmi3InstanceEnvironment env = m->env;
    fmi3LogMessageCallback log = m->log;
    defaults(m);
    m->env = env;
    m->log = log;
    return fmi3OK;
}

/* ------------------------------------------------------------------ getting and setting */
fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 values[],
                          size_t nValues) {
    Model *m = instance;
    size_t i, at = 0;
    for (i = 0; i < nvr; i++) {
        int n = get_values(m, vr[i], values + at, nValues - at);
        if (n < 0) { fail(m, "fmi3GetFloat64: unknown value reference or too few values"); return fmi3Error; }
        at += (size_t)n;
    }
    return at == nValues ? fmi3OK : fmi3Error;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Float64 values[], size_t nValues) {
    Model *m = instance;
    size_t i, at = 0;
    for (i = 0; i < nvr; i++) {
        int n = set_values(m, vr[i], values + at, nValues - at);
        if (n < 0) { fail(m, "fmi3SetFloat64: value reference not settable or too few values"); return fmi3Error; }
        at += (size_t)n;
    }
    return at == nValues ? fmi3OK : fmi3Error;
}

#define UNSUPPORTED_GET(NAME, T) \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, T values[], size_t nValues) { \
        (void)vr; (void)nvr; (void)values; (void)nValues; fail(instance, #NAME ": no such variables"); \
        return fmi3Error; }
#define UNSUPPORTED_SET(NAME, T) \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const T values[], \
                    size_t nValues) { \
        (void)vr; (void)nvr; (void)values; (void)nValues; fail(instance, #NAME ": no such variables"); \
        return fmi3Error; }
UNSUPPORTED_GET(fmi3GetFloat32, fmi3Float32)
UNSUPPORTED_GET(fmi3GetInt8, fmi3Int8)
UNSUPPORTED_GET(fmi3GetUInt8, fmi3UInt8)
UNSUPPORTED_GET(fmi3GetInt16, fmi3Int16)
UNSUPPORTED_GET(fmi3GetUInt16, fmi3UInt16)
fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Int32 values[],
                        size_t nValues) {
    Model *m = instance;
    size_t i;
    if (nvr != nValues) return fmi3Error;
    for (i = 0; i < nvr; i++) {
        if (vr[i] == VR_SCALE_EXP) values[i] = m->scale_exp;
        else if (vr[i] == VR_N_STEPS) values[i] = m->n_steps;
        else { fail(m, "fmi3GetInt32: unknown value reference"); return fmi3Error; }
    }
    return fmi3OK;
}
UNSUPPORTED_GET(fmi3GetUInt32, fmi3UInt32)
UNSUPPORTED_GET(fmi3GetInt64, fmi3Int64)
UNSUPPORTED_GET(fmi3GetUInt64, fmi3UInt64)
fmi3Status fmi3GetBoolean(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Boolean values[],
                          size_t nValues) {
    Model *m = instance;
    if (nvr != 1 || nValues != 1 || vr[0] != VR_NEGATE) { fail(m, "fmi3GetBoolean: unknown value reference"); return fmi3Error; }
    values[0] = m->negate;
    return fmi3OK;
}
UNSUPPORTED_GET(fmi3GetString, fmi3String)
UNSUPPORTED_SET(fmi3SetFloat32, fmi3Float32)
UNSUPPORTED_SET(fmi3SetInt8, fmi3Int8)
UNSUPPORTED_SET(fmi3SetUInt8, fmi3UInt8)
UNSUPPORTED_SET(fmi3SetInt16, fmi3Int16)
UNSUPPORTED_SET(fmi3SetUInt16, fmi3UInt16)
fmi3Status fmi3SetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const fmi3Int32 values[],
                        size_t nValues) {
    Model *m = instance;
    if (nvr != 1 || nValues != 1 || vr[0] != VR_SCALE_EXP) { fail(m, "fmi3SetInt32: not settable"); return fmi3Error; }
    m->scale_exp = values[0];
    return fmi3OK;
}
UNSUPPORTED_SET(fmi3SetUInt32, fmi3UInt32)
UNSUPPORTED_SET(fmi3SetInt64, fmi3Int64)
UNSUPPORTED_SET(fmi3SetUInt64, fmi3UInt64)
fmi3Status fmi3SetBoolean(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Boolean values[], size_t nValues) {
    Model *m = instance;
    if (nvr != 1 || nValues != 1 || vr[0] != VR_NEGATE) { fail(m, "fmi3SetBoolean: not settable"); return fmi3Error; }
    m->negate = values[0];
    return fmi3OK;
}
UNSUPPORTED_SET(fmi3SetString, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, size_t valueSizes[],
                         fmi3Binary values[], size_t nValues) {
    (void)instance; (void)vr; (void)nvr; (void)valueSizes; (void)values; (void)nValues; return fmi3Error;
}
fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const size_t valueSizes[],
                         const fmi3Binary values[], size_t nValues) {
    (void)instance; (void)vr; (void)nvr; (void)valueSizes; (void)values; (void)nValues; return fmi3Error;
}
fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Clock values[]) {
    (void)instance; (void)vr; (void)nvr; (void)values; return fmi3Error;
}
fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const fmi3Clock values[]) {
    (void)instance; (void)vr; (void)nvr; (void)values; return fmi3Error;
}

/* ------------------------------------------------------------------ what this model does not offer */
fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies) {
    (void)instance; (void)valueReference; (void)nDependencies; return fmi3Error;
}
fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[],
                                       size_t nDependencies) {
    (void)instance; (void)dependent; (void)elementIndicesOfDependent; (void)independents;
    (void)elementIndicesOfIndependents; (void)dependencyKinds; (void)nDependencies; return fmi3Error;
}
fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    (void)instance; (void)FMUState; return fmi3Error;
}
fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    (void)instance; (void)FMUState; return fmi3Error;
}
fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    (void)instance; (void)FMUState; return fmi3Error;
}
fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size) {
    (void)instance; (void)FMUState; (void)size; return fmi3Error;
}
fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size) {
    (void)instance; (void)FMUState; (void)serializedState; (void)size; return fmi3Error;
}
fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState) {
    (void)instance; (void)serializedState; (void)size; (void)FMUState; return fmi3Error;
}
fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                        size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)instance; (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed;
    (void)sensitivity; (void)nSensitivity; return fmi3Error;
}
fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)instance; (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed;
    (void)sensitivity; (void)nSensitivity; return fmi3Error;
}
fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) { (void)instance; return fmi3Error; }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) { (void)instance; return fmi3Error; }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                  fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[]) {
    (void)instance; (void)vr; (void)nvr; (void)intervals; (void)qualifiers; return fmi3Error;
}
fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                   fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[]) {
    (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; (void)qualifiers; return fmi3Error;
}
fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 shifts[]) {
    (void)instance; (void)vr; (void)nvr; (void)shifts; return fmi3Error;
}
fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                fmi3UInt64 counters[], fmi3UInt64 resolutions[]) {
    (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; return fmi3Error;
}
fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                  const fmi3Float64 intervals[]) {
    (void)instance; (void)vr; (void)nvr; (void)intervals; return fmi3Error;
}
fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                   const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; return fmi3Error;
}
fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                               const fmi3Float64 shifts[]) {
    (void)instance; (void)vr; (void)nvr; (void)shifts; return fmi3Error;
}
fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    (void)instance; (void)vr; (void)nvr; (void)counters; (void)resolutions; return fmi3Error;
}
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) { (void)instance; return fmi3OK; }
fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime) {
    (void)instance; (void)clockReference; (void)activationTime; return fmi3Error;
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime) {
    (void)instance;
    *discreteStatesNeedUpdate = fmi3False;
    *terminateSimulation = fmi3False;
    *nominalsOfContinuousStatesChanged = fmi3False;
    *valuesOfContinuousStatesChanged = fmi3False;
    *nextEventTimeDefined = fmi3False;
    *nextEventTime = 0.0;
    return fmi3OK;
}

/* ------------------------------------------------------------------ model exchange */
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) { (void)instance; return fmi3OK; }
fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation) {
    (void)instance; (void)noSetFMUStatePriorToCurrentPoint;
    *enterEventMode = fmi3False;
    *terminateSimulation = fmi3False;
    return fmi3OK;
}
fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) { ((Model *)instance)->time = time; return fmi3OK; }
fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 x[], size_t nx) {
    Model *m = instance;
    if (nx != 2) return fmi3Error;
    m->x[0] = x[0]; m->x[1] = x[1];
    return fmi3OK;
}
fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 dx[], size_t nx) {
    Model *m = instance;
    if (nx != 2) return fmi3Error;
    dx[0] = m->u - m->k[0] * m->x[0];
    dx[1] = m->u - m->k[1] * m->x[1];
    return fmi3OK;
}
fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 z[], size_t nz) {
    (void)instance; (void)z; return nz == 0 ? fmi3OK : fmi3Error;
}
fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 x[], size_t nx) {
    Model *m = instance;
    if (nx != 2) return fmi3Error;
    x[0] = m->x[0]; x[1] = m->x[1];
    return fmi3OK;
}
fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nx) {
    size_t i;
    (void)instance;
    for (i = 0; i < nx; i++) nominals[i] = 1.0;
    return fmi3OK;
}
fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *n) { (void)instance; *n = 0; return fmi3OK; }
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *n) { (void)instance; *n = 2; return fmi3OK; }

/* ------------------------------------------------------------------ co-simulation */
fmi3Status fmi3EnterStepMode(fmi3Instance instance) { (void)instance; return fmi3OK; }
fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                    const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues) {
    (void)instance; (void)vr; (void)nvr; (void)orders; (void)values; (void)nValues; return fmi3Error;
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                      fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn,
                      fmi3Float64 *lastSuccessfulTime) {
    Model *m = instance;
    int i;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!m->initialised) { fail(m, "fmi3DoStep before initialisation"); return fmi3Error; }
    for (i = 0; i < 2; i++) {   /* the exact flow of x' = u - k x over the step */
        double xs = m->u / m->k[i];
        m->x[i] = xs + (m->x[i] - xs) * exp(-m->k[i] * communicationStepSize);
    }
    m->time = currentCommunicationPoint + communicationStepSize;
    m->n_steps++;
    *eventHandlingNeeded = fmi3False;
    *terminateSimulation = m->time >= m->t_terminate ? fmi3True : fmi3False;
    *earlyReturn = fmi3False;
    *lastSuccessfulTime = m->time;
    return fmi3OK;
}
