/* Crash: an FMI 2.0 co-simulation binary that takes any model description's variables and kills its process
 * as its first run starts (a test fixture of fmusa: an FMU that crashes, as exports do in real life).
 *
 * Every Real, Integer and Boolean reads 0 and can be set (Strings cannot); fmi2EnterInitializationMode
 * calls abort() (SIGABRT), or with -DCRASH_SEGV writes through a NULL pointer (SIGSEGV). Built by
 * tests/test_diagnose_pool.py with the ScrewVertebra model description, so that a diagnosis sets its
 * parameters as it would the real FMU's, and then dies:
 *   gcc -shared -fPIC -O1 -I <fmpy>/c-code crash.c -o Crash.so
 */
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#define FMUSA_TEST_OWN_BOOLEANS
#include "../common/cs_stubs.h"

static int instance;

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[]) {
    (void)c; (void)on; (void)n; (void)cats; return fmi2OK;
}
fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible, fmi2Boolean logging) {
    (void)name; (void)guid; (void)resources; (void)functions; (void)visible; (void)logging;
    return type == fmi2CoSimulation ? (fmi2Component)&instance : NULL;
}
void fmi2FreeInstance(fmi2Component c) { (void)c; }
fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean td, fmi2Real tol, fmi2Real t0, fmi2Boolean sd,
                               fmi2Real t1) {
    (void)c; (void)td; (void)tol; (void)t0; (void)sd; (void)t1; return fmi2OK;
}
fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    (void)c;
#ifdef CRASH_SEGV
    { volatile int *volatile p = NULL; *p = 42; }
#endif
    abort();
    return fmi2Error;
}
fmi2Status fmi2ExitInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    (void)c; (void)vr; memset(v, 0, n * sizeof *v); return fmi2OK;
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[]) {
    (void)c; (void)vr; memset(v, 0, n * sizeof *v); return fmi2OK;
}
fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Real v[]) {
    (void)c; (void)vr; (void)n; (void)v; return fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[]) {
    (void)c; (void)vr; (void)n; (void)v; return fmi2OK;
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[]) {
    (void)c; (void)vr; memset(v, 0, n * sizeof *v); return fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[]) {
    (void)c; (void)vr; (void)n; (void)v; return fmi2OK;
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    (void)c; (void)t; (void)h; (void)noSetPrior; return fmi2Error;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
