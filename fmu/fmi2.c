/* FMI 2.0 layer of fmusa's FMUs (ScrewVertebra, InterfaceElement): state machine, argument checks, logging.
 * The equations live in the model's glue (model.c, element.c) behind model.h; nothing here knows the physics.
 * Co-simulation always; model exchange and getting/setting the FMU state where model.h says MODEL_ME and
 * MODEL_FMU_STATE (in the style of the Modelica Reference FMUs). Every call checks that it is allowed in the
 * current state and that its arguments are valid, and reports problems through the logger callback. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

typedef enum {
    ST_INSTANTIATED = 1 << 0,
    ST_INIT = 1 << 1,
    ST_STEP_COMPLETE = 1 << 2,
    ST_STEP_FAILED = 1 << 3,
    ST_TERMINATED = 1 << 4,
    ST_ERROR = 1 << 5,
    ST_EVENT_MODE = 1 << 6,        /* model exchange */
    ST_CONT_TIME = 1 << 7,
} State;

#define ST_ANY (ST_INSTANTIATED | ST_INIT | ST_STEP_COMPLETE | ST_STEP_FAILED | ST_TERMINATED | ST_ERROR \
                | ST_EVENT_MODE | ST_CONT_TIME)
#define ST_ME_RUNNING (ST_EVENT_MODE | ST_CONT_TIME)
#define ST_RUNNING (ST_STEP_COMPLETE | ST_STEP_FAILED | ST_ME_RUNNING)
#define ST_READABLE (ST_INIT | ST_STEP_COMPLETE | ST_STEP_FAILED | ST_TERMINATED | ST_ERROR)

typedef struct {
    ModelInstance model;
    fmi2Type type;
    State state;
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    fmi2Boolean logging_on;
    double start_time, stop_time;
    fmi2Boolean stop_time_defined;
    /* the experiment's tolerance (0: none), applied when initialisation ends, so that parameters set
       before or after fmi2SetupExperiment (both are allowed) meet the same rule */
    double tolerance;
    double last_successful_time;
} Instance;

static void log_msg(Instance *c, fmi2Status status, const char *category, const char *fmt, ...)
{
    if (!c || !c->logger) return;
    if (status < fmi2Error && !c->logging_on) return;   /* errors are always reported */
    char buf[1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    c->logger(c->env, c->name, status, category, "%s", buf);
}

#define ERR(c, ...) log_msg((c), fmi2Error, "logStatusError", __VA_ARGS__)

static fmi2Status fail(Instance *c, const char *fmt_fn, const char *detail)
{
    ERR(c, "%s: %s", fmt_fn, detail);
    return fmi2Error;
}

static int allowed(Instance *c, const char *fn, int states)
{
    if (!c) return 0;
    if (!(c->state & states)) {
        ERR(c, "%s: not allowed in the current state (%d)", fn, (int)c->state);
        c->state = ST_ERROR;
        return 0;
    }
    return 1;
}

static int null_args(Instance *c, const char *fn, const void *vr, size_t nvr, const void *value)
{
    if (nvr > 0 && (vr == NULL || value == NULL)) {
        ERR(c, "%s: vr or value is NULL", fn);
        return 1;
    }
    return 0;
}

/* ------------------------------------------------------------------ inquiry, instantiation */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component comp, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    Instance *c = comp;
    (void)categories;
    if (!allowed(c, "fmi2SetDebugLogging", ST_ANY)) return fmi2Error;
    if (nCategories > 0 && categories == NULL) return fail(c, "fmi2SetDebugLogging", "categories is NULL");
    c->logging_on = loggingOn;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn)
{
    (void)fmuResourceLocation;
    (void)visible;
    fmi2CallbackLogger logger = functions ? functions->logger : NULL;
    fmi2ComponentEnvironment env = functions ? functions->componentEnvironment : NULL;
    const char *name = instanceName ? instanceName : "?";
    if (!instanceName || !*instanceName) {
        if (logger) logger(env, name, fmi2Error, "logStatusError", "fmi2Instantiate: missing instance name");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation && !(MODEL_ME && fmuType == fmi2ModelExchange)) {
        if (logger) logger(env, name, fmi2Error, "logStatusError",
                           "fmi2Instantiate: " MODEL_NAME " supports co-simulation only");
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        if (logger) logger(env, name, fmi2Error, "logStatusError",
                           "fmi2Instantiate: GUID %s does not match the binary's %s", fmuGUID ? fmuGUID : "NULL",
                           MODEL_GUID);
        return NULL;
    }
    Instance *c = calloc(1, sizeof(Instance));
    if (!c) return NULL;
    c->name = malloc(strlen(instanceName) + 1);
    if (!c->name) { free(c); return NULL; }
    strcpy(c->name, instanceName);
    c->logger = logger;
    c->env = env;
    c->logging_on = loggingOn;
    c->type = fmuType;
    model_set_start_values(&c->model);
    c->state = ST_INSTANTIATED;
    return c;
}

void fmi2FreeInstance(fmi2Component comp)
{
    Instance *c = comp;
    if (!c) return;
    model_free(&c->model);
    free(c->name);
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component comp, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2SetupExperiment", ST_INSTANTIATED)) return fmi2Error;
    if (!isfinite(startTime)) return fail(c, "fmi2SetupExperiment", "startTime is not finite");
    if (stopTimeDefined && !(stopTime >= startTime))
        return fail(c, "fmi2SetupExperiment", "stopTime is before startTime");
    c->tolerance = (toleranceDefined && isfinite(tolerance) && tolerance > 0.0) ? tolerance : 0.0;
    c->start_time = startTime;
    c->stop_time = stopTime;
    c->stop_time_defined = stopTimeDefined;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component comp)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2EnterInitializationMode", ST_INSTANTIATED)) return fmi2Error;
    c->state = ST_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    Instance *c = comp;
    char msg[512];
    if (!allowed(c, "fmi2ExitInitializationMode", ST_INIT)) return fmi2Error;
    /* the experiment tolerance tightens (never loosens) the solver tolerance */
    if (c->tolerance > 0.0 && c->tolerance < c->model.v[VR_rtol]) c->model.v[VR_rtol] = fmax(c->tolerance, 1e-14);
    if (model_validate(&c->model, msg, sizeof msg) ||
        model_initialize(&c->model, c->start_time, msg, sizeof msg)) {
        c->state = ST_ERROR;
        return fail(c, "fmi2ExitInitializationMode", msg);
    }
    c->last_successful_time = c->start_time;
    c->state = c->type == fmi2ModelExchange ? ST_EVENT_MODE : ST_STEP_COMPLETE;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component comp)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2Terminate", ST_RUNNING)) return fmi2Error;
    log_msg(c, fmi2OK, "logAll", "terminated at t = %g after %ld steps (%ld rejected, %ld rhs evaluations)",
            c->model.time, MODEL_N_STEPS(&c->model), MODEL_N_REJECTED(&c->model), MODEL_N_RHS(&c->model));
    c->state = ST_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component comp)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2Reset", ST_ANY)) return fmi2Error;
    model_set_start_values(&c->model);
    c->state = ST_INSTANTIATED;
    c->stop_time_defined = fmi2False;
    c->tolerance = 0.0;
    return fmi2OK;
}

/* ------------------------------------------------------------------ get / set */

static fmi2Status get_values(Instance *c, const char *fn, const fmi2ValueReference vr[], size_t nvr,
                             VarType type, void *value)
{
    if (!allowed(c, fn, ST_ANY)) return fmi2Error;
    if (null_args(c, fn, vr, nvr, value)) return fmi2Error;
    if (c->state & (ST_RUNNING | ST_TERMINATED)) model_refresh(&c->model);
    for (size_t i = 0; i < nvr; i++) {
        const VarInfo *info = model_variable(vr[i]);
        if (!info || info->type != type) {
            ERR(c, "%s: unknown value reference %u for this type", fn, vr[i]);
            return fmi2Error;
        }
        double x = c->model.v[vr[i]];
        if (type == TYPE_REAL) ((fmi2Real *)value)[i] = x;
        else if (type == TYPE_INTEGER) ((fmi2Integer *)value)[i] = (fmi2Integer)x;
        else ((fmi2Boolean *)value)[i] = x != 0.0;
    }
    return fmi2OK;
}

static fmi2Status set_values(Instance *c, const char *fn, const fmi2ValueReference vr[], size_t nvr,
                             VarType type, const void *value)
{
    if (!allowed(c, fn, ST_INSTANTIATED | ST_INIT | ST_RUNNING)) return fmi2Error;
    if (null_args(c, fn, vr, nvr, value)) return fmi2Error;
    for (size_t i = 0; i < nvr; i++) {
        const VarInfo *info = model_variable(vr[i]);
        if (!info || info->type != type) {
            ERR(c, "%s: unknown value reference %u for this type", fn, vr[i]);
            return fmi2Error;
        }
        if (info->causality == CAUS_CALCULATED || info->causality == CAUS_OUTPUT || info->causality == CAUS_LOCAL) {
            ERR(c, "%s: %s is %s and cannot be set", fn, info->name,
                info->causality == CAUS_OUTPUT ? "an output" :
                info->causality == CAUS_LOCAL ? "a local variable" : "a calculated parameter");
            return fmi2Error;
        }
        if (info->causality == CAUS_PARAMETER && !(c->state & (ST_INSTANTIATED | ST_INIT))) {
            ERR(c, "%s: parameter %s is fixed after initialisation; call fmi2Reset to change it", fn, info->name);
            return fmi2Error;
        }
        double x;
        if (type == TYPE_REAL) {
            x = ((const fmi2Real *)value)[i];
            if (info->causality == CAUS_INPUT && !isfinite(x)) {
                ERR(c, "%s: input %s = %g is not finite", fn, info->name, x);
                return fmi2Error;
            }
        } else if (type == TYPE_INTEGER) {
            x = ((const fmi2Integer *)value)[i];
        } else {
            x = ((const fmi2Boolean *)value)[i] ? 1.0 : 0.0;
        }
        c->model.v[vr[i]] = x;
        if (info->causality == CAUS_INPUT) {
            c->model.t_inputs = c->model.time;
            MODEL_TOUCH(&c->model);
        }
    }
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[])
{
    return get_values(c, "fmi2GetReal", vr, nvr, TYPE_REAL, value);
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])
{
    return get_values(c, "fmi2GetInteger", vr, nvr, TYPE_INTEGER, value);
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[])
{
    return get_values(c, "fmi2GetBoolean", vr, nvr, TYPE_BOOLEAN, value);
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[])
{
    (void)value;
    if (nvr == 0) return fmi2OK;
    (void)vr;
    return fail(c, "fmi2GetString", "the model has no String variables");
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[])
{
    return set_values(c, "fmi2SetReal", vr, nvr, TYPE_REAL, value);
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[])
{
    return set_values(c, "fmi2SetInteger", vr, nvr, TYPE_INTEGER, value);
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[])
{
    return set_values(c, "fmi2SetBoolean", vr, nvr, TYPE_BOOLEAN, value);
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[])
{
    (void)value;
    (void)vr;
    if (nvr == 0) return fmi2OK;
    return fail(c, "fmi2SetString", "the model has no String variables");
}

/* ------------------------------------------------------------------ FMU state */

#if MODEL_FMU_STATE
/* The model instance holds no pointers: a state is a copy of it, with the FMI state and time. */
typedef struct {
    ModelInstance model;
    State state;
    double last_successful_time;
} Snapshot;

fmi2Status fmi2GetFMUstate(fmi2Component comp, fmi2FMUstate *s)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2GetFMUstate", ST_INSTANTIATED | ST_INIT | ST_RUNNING | ST_TERMINATED)) return fmi2Error;
    if (!s) return fail(c, "fmi2GetFMUstate", "FMUstate is NULL");
    Snapshot *snap = *s ? (Snapshot *)*s : malloc(sizeof(Snapshot));   /* a given state is overwritten */
    if (!snap) return fail(c, "fmi2GetFMUstate", "out of memory");
    snap->model = c->model;
    snap->state = c->state;
    snap->last_successful_time = c->last_successful_time;
    *s = snap;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component comp, fmi2FMUstate s)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2SetFMUstate", ST_INSTANTIATED | ST_INIT | ST_RUNNING | ST_TERMINATED)) return fmi2Error;
    if (!s) return fail(c, "fmi2SetFMUstate", "FMUstate is NULL");
    const Snapshot *snap = s;
    c->model = snap->model;
    c->state = snap->state;
    c->last_successful_time = snap->last_successful_time;
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component comp, fmi2FMUstate *s)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2FreeFMUstate", ST_ANY)) return fmi2Error;
    if (!s) return fail(c, "fmi2FreeFMUstate", "FMUstate is NULL");
    free(*s);
    *s = NULL;
    return fmi2OK;
}
#else
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s)
{
    (void)s;
    return fail(c, "fmi2GetFMUstate", "not supported (canGetAndSetFMUstate = false)");
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s)
{
    (void)s;
    return fail(c, "fmi2SetFMUstate", "not supported (canGetAndSetFMUstate = false)");
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s)
{
    (void)s;
    return fail(c, "fmi2FreeFMUstate", "not supported (canGetAndSetFMUstate = false)");
}
#endif

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *size)
{
    (void)s;
    (void)size;
    return fail(c, "fmi2SerializedFMUstateSize", "not supported");
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t size)
{
    (void)s;
    (void)b;
    (void)size;
    return fail(c, "fmi2SerializeFMUstate", "not supported");
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t size, fmi2FMUstate *s)
{
    (void)b;
    (void)size;
    (void)s;
    return fail(c, "fmi2DeSerializeFMUstate", "not supported");
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real du[],
                                        fmi2Real dz[])
{
    (void)u; (void)nu; (void)z; (void)nz; (void)du; (void)dz;
    return fail(c, "fmi2GetDirectionalDerivative", "not supported");
}

/* ------------------------------------------------------------------ co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    Instance *c = comp;
    if (!allowed(c, "fmi2SetRealInputDerivatives", ST_INSTANTIATED | ST_INIT | ST_STEP_COMPLETE | ST_STEP_FAILED))
        return fmi2Error;
    if (null_args(c, "fmi2SetRealInputDerivatives", vr, nvr, value) || (nvr > 0 && !order)) return fmi2Error;
    for (size_t i = 0; i < nvr; i++) {
        const VarInfo *info = model_variable(vr[i]);
        if (!info || info->causality != CAUS_INPUT || info->type != TYPE_REAL) {
            ERR(c, "fmi2SetRealInputDerivatives: value reference %u is not a Real input", vr[i]);
            return fmi2Error;
        }
        if (order[i] != 1) {
            ERR(c, "fmi2SetRealInputDerivatives: order %d for %s: only first derivatives are used", order[i],
                info->name);
            return fmi2Error;
        }
        if (!isfinite(value[i])) {
            ERR(c, "fmi2SetRealInputDerivatives: derivative of %s is not finite", info->name);
            return fmi2Error;
        }
            c->model.dv[vr[i]] = value[i];
    }
    MODEL_TOUCH(&c->model);
    return fmi2OK;
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[])
{
    (void)vr; (void)nvr; (void)order; (void)value;
    return fail(c, "fmi2GetRealOutputDerivatives", "not supported (maxOutputDerivativeOrder = 0)");
}

fmi2Status fmi2DoStep(fmi2Component comp, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    Instance *c = comp;
    char msg[512];
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!allowed(c, "fmi2DoStep", ST_STEP_COMPLETE)) return fmi2Error;
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize))
        return fail(c, "fmi2DoStep", "communicationStepSize must be > 0");
    double t = c->model.time;
    if (fabs(currentCommunicationPoint - t) > 1e-9 * fmax(1.0, fabs(t))) {
        snprintf(msg, sizeof msg, "currentCommunicationPoint %.17g does not match the FMU's time %.17g",
                 currentCommunicationPoint, t);
        return fail(c, "fmi2DoStep", msg);
    }
    double t_end = currentCommunicationPoint + communicationStepSize;
    if (c->stop_time_defined && t_end > c->stop_time * (1.0 + 1e-12) + 1e-12) {
        snprintf(msg, sizeof msg, "step to %.17g passes the stop time %.17g", t_end, c->stop_time);
        return fail(c, "fmi2DoStep", msg);
    }
    if (model_do_step(&c->model, t_end, msg, sizeof msg)) {
        c->state = ST_STEP_FAILED;
        ERR(c, "fmi2DoStep from t = %.17g: %s", currentCommunicationPoint, msg);
        return fmi2Error;
    }
    c->last_successful_time = t_end;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c)
{
    return fail(c, "fmi2CancelStep", "doStep is synchronous; there is nothing to cancel");
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{
    (void)s;
    (void)value;
    return fail(c, "fmi2GetStatus", "doStep is synchronous; no pending status");
}

fmi2Status fmi2GetRealStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Real *value)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2GetRealStatus", ST_ANY)) return fmi2Error;
    if (s == fmi2LastSuccessfulTime && value) {
        *value = c->last_successful_time;
        return fmi2OK;
    }
    return fail(c, "fmi2GetRealStatus", "only fmi2LastSuccessfulTime is available");
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{
    (void)s;
    (void)value;
    return fail(c, "fmi2GetIntegerStatus", "no integer status");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Boolean *value)
{
    Instance *c = comp;
    if (s == fmi2Terminated && value) {
        if (!allowed(c, "fmi2GetBooleanStatus", ST_ANY)) return fmi2Error;
        *value = fmi2False;
        return fmi2OK;
    }
    return fail(c, "fmi2GetBooleanStatus", "only fmi2Terminated is available");
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{
    (void)s;
    (void)value;
    return fail(c, "fmi2GetStringStatus", "no string status");
}

/* ------------------------------------------------------------------ model exchange */

#if MODEL_ME
fmi2Status fmi2EnterEventMode(fmi2Component comp)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2EnterEventMode", ST_ME_RUNNING)) return fmi2Error;
    c->state = ST_EVENT_MODE;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component comp, fmi2EventInfo *info)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2NewDiscreteStates", ST_EVENT_MODE)) return fmi2Error;
    if (!info) return fail(c, "fmi2NewDiscreteStates", "fmi2EventInfo is NULL");
    /* no discrete states, no time or state events: the model is continuous */
    info->newDiscreteStatesNeeded = fmi2False;
    info->terminateSimulation = fmi2False;
    info->nominalsOfContinuousStatesChanged = fmi2False;
    info->valuesOfContinuousStatesChanged = fmi2False;
    info->nextEventTimeDefined = fmi2False;
    info->nextEventTime = 0.0;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component comp)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2EnterContinuousTimeMode", ST_EVENT_MODE)) return fmi2Error;
    c->state = ST_CONT_TIME;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component comp, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation)
{
    Instance *c = comp;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!allowed(c, "fmi2CompletedIntegratorStep", ST_CONT_TIME)) return fmi2Error;
    if (!enterEventMode || !terminateSimulation)
        return fail(c, "fmi2CompletedIntegratorStep", "enterEventMode or terminateSimulation is NULL");
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component comp, fmi2Real time)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2SetTime", ST_ME_RUNNING)) return fmi2Error;
    if (!isfinite(time)) return fail(c, "fmi2SetTime", "time is not finite");
    c->model.time = time;
    c->model.t_inputs = time;   /* model exchange: the inputs are the values set, no extrapolation */
    MODEL_TOUCH(&c->model);
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component comp, const fmi2Real x[], size_t nx)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2SetContinuousStates", ST_CONT_TIME)) return fmi2Error;
    if (nx != NX) {
        ERR(c, "fmi2SetContinuousStates: nx = %zu, the model has %d states", nx, NX);
        return fmi2Error;
    }
    if (!x) return fail(c, "fmi2SetContinuousStates", "x is NULL");
    for (size_t i = 0; i < nx; i++)
        if (!isfinite(x[i])) {
            ERR(c, "fmi2SetContinuousStates: state %zu = %g is not finite", i, x[i]);
            return fmi2Error;
        }
    model_set_states(&c->model, x);
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component comp, fmi2Real derivatives[], size_t nx)
{
    Instance *c = comp;
    char msg[512];
    if (!allowed(c, "fmi2GetDerivatives", ST_INIT | ST_ME_RUNNING | ST_TERMINATED | ST_ERROR)) return fmi2Error;
    if (nx != NX) {
        ERR(c, "fmi2GetDerivatives: nx = %zu, the model has %d states", nx, NX);
        return fmi2Error;
    }
    if (!derivatives) return fail(c, "fmi2GetDerivatives", "derivatives is NULL");
    if (model_derivatives(&c->model, derivatives, msg, sizeof msg)) return fail(c, "fmi2GetDerivatives", msg);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component comp, fmi2Real eventIndicators[], size_t ni)
{
    Instance *c = comp;
    (void)eventIndicators;
    if (!allowed(c, "fmi2GetEventIndicators", ST_INIT | ST_ME_RUNNING | ST_TERMINATED | ST_ERROR)) return fmi2Error;
    if (ni != 0) {
        ERR(c, "fmi2GetEventIndicators: ni = %zu, the model has no event indicators", ni);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component comp, fmi2Real x[], size_t nx)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2GetContinuousStates", ST_INIT | ST_ME_RUNNING | ST_TERMINATED | ST_ERROR)) return fmi2Error;
    if (nx != NX) {
        ERR(c, "fmi2GetContinuousStates: nx = %zu, the model has %d states", nx, NX);
        return fmi2Error;
    }
    if (!x) return fail(c, "fmi2GetContinuousStates", "x is NULL");
    model_get_states(&c->model, x);
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component comp, fmi2Real x_nominal[], size_t nx)
{
    Instance *c = comp;
    if (!allowed(c, "fmi2GetNominalsOfContinuousStates", ST_ANY & ~ST_ERROR)) return fmi2Error;
    if (nx != NX) {
        ERR(c, "fmi2GetNominalsOfContinuousStates: nx = %zu, the model has %d states", nx, NX);
        return fmi2Error;
    }
    if (!x_nominal) return fail(c, "fmi2GetNominalsOfContinuousStates", "x_nominal is NULL");
    for (size_t i = 0; i < nx; i++) x_nominal[i] = 1.0;
    return fmi2OK;
}
#endif
