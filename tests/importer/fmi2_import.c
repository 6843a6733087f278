/* A minimal FMI 2.0 co-simulation importer, independent of fmpy: load the FMU's shared library, look
 * the fmi2 functions up by name, instantiate, set variables, initialise, take ONE doStep to the stop
 * time and print the requested Real variables.  Builds for Linux (dlopen) and, with mingw-w64, for
 * Windows (LoadLibrary) so that the win64 DLL of the FMU can be run under wine.
 *
 * usage: fmi2_import LIBRARY GUID STOP_TIME [SET...] -- GET...
 *   SET  r:VR=VALUE (Real), i:VR=VALUE (Integer), b:VR=0|1 (Boolean); VALUE of a Real may be a decimal
 *        number or x followed by the 16 hex digits of its IEEE-754 bits (exact whatever the C runtime's
 *        strtod does)
 *   GET  VR of a Real variable, printed after the step as "VR HEXBITS %.17g" on its own line
 * Exit status: 0 when every call returned fmi2OK, 1 on a usage or loading error, 2 on an FMI error.
 * The FMU's log messages go to stderr. */
#include <inttypes.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2FunctionTypes.h"

#ifdef _WIN32
#include <windows.h>
typedef HMODULE Lib;
static Lib lib_open(const char *p) { return LoadLibraryA(p); }
static void *lib_sym(Lib l, const char *n) { return (void *)GetProcAddress(l, n); }
static void lib_close(Lib l) { FreeLibrary(l); }
static const char *lib_error(void)
{
    static char buf[64];
    snprintf(buf, sizeof buf, "Windows error %lu", (unsigned long)GetLastError());
    return buf;
}
#else
#include <dlfcn.h>
typedef void *Lib;
static Lib lib_open(const char *p) { return dlopen(p, RTLD_NOW | RTLD_LOCAL); }
static void *lib_sym(Lib l, const char *n) { return dlsym(l, n); }
static void lib_close(Lib l) { dlclose(l); }
static const char *lib_error(void) { const char *e = dlerror(); return e ? e : "unknown error"; }
#endif

#define MAX_SET 256
#define MAX_GET 256

static void logger(fmi2ComponentEnvironment env, fmi2String name, fmi2Status status, fmi2String category,
                   fmi2String message, ...)
{
    (void)env;
    va_list ap;
    va_start(ap, message);
    fprintf(stderr, "[%s] status %d %s: ", name ? name : "?", (int)status, category ? category : "");
    vfprintf(stderr, message, ap);
    fputc('\n', stderr);
    va_end(ap);
}

static double bits_to_double(uint64_t u) { double d; memcpy(&d, &u, sizeof d); return d; }
static uint64_t double_to_bits(double d) { uint64_t u; memcpy(&u, &d, sizeof u); return u; }

static int parse_real(const char *s, double *out)
{
    char *end;
    if (s[0] == 'x') {
        uint64_t u = strtoull(s + 1, &end, 16);
        if (end == s + 1 || *end) return 0;
        *out = bits_to_double(u);
        return 1;
    }
    *out = strtod(s, &end);
    return end != s && !*end;
}

#define LOOKUP(var, type, name)                                                                         \
    type var = (type)lib_sym(lib, name);                                                                \
    if (!var) { fprintf(stderr, "fmi2_import: %s not found in %s\n", name, argv[1]); return 1; }

#define CHECK(call)                                                                                     \
    do {                                                                                                \
        fmi2Status st_ = (call);                                                                        \
        if (st_ != fmi2OK) { fprintf(stderr, "fmi2_import: %s returned %d\n", #call, (int)st_); return 2; } \
    } while (0)

int main(int argc, char **argv)
{
    if (argc < 5) {
        fprintf(stderr, "usage: %s LIBRARY GUID STOP_TIME [r:VR=V|i:VR=V|b:VR=V]... -- VR...\n", argv[0]);
        return 1;
    }
    double stop;
    if (!parse_real(argv[3], &stop)) { fprintf(stderr, "fmi2_import: bad stop time %s\n", argv[3]); return 1; }

    fmi2ValueReference rvr[MAX_SET], ivr[MAX_SET], bvr[MAX_SET], gvr[MAX_GET];
    fmi2Real rv[MAX_SET], gv[MAX_GET];
    fmi2Integer iv[MAX_SET];
    fmi2Boolean bv[MAX_SET];
    size_t nr = 0, ni = 0, nb = 0, ng = 0;
    int i = 4;
    for (; i < argc && strcmp(argv[i], "--") != 0; i++) {
        const char *a = argv[i];
        char *eq = strchr(a, '=');
        unsigned long vr;
        char *end;
        if (strlen(a) < 4 || a[1] != ':' || !eq || nr >= MAX_SET || ni >= MAX_SET || nb >= MAX_SET) goto bad;
        vr = strtoul(a + 2, &end, 10);
        if (end != eq) goto bad;
        switch (a[0]) {
        case 'r':
            if (!parse_real(eq + 1, &rv[nr])) goto bad;
            rvr[nr++] = (fmi2ValueReference)vr;
            break;
        case 'i':
            iv[ni] = (fmi2Integer)strtol(eq + 1, &end, 10);
            if (*end) goto bad;
            ivr[ni++] = (fmi2ValueReference)vr;
            break;
        case 'b':
            bv[nb] = strcmp(eq + 1, "0") != 0 && strcmp(eq + 1, "false") != 0;
            bvr[nb++] = (fmi2ValueReference)vr;
            break;
        default:
            goto bad;
        }
        continue;
    bad:
        fprintf(stderr, "fmi2_import: bad argument %s\n", a);
        return 1;
    }
    for (i++; i < argc; i++) {
        char *end;
        if (ng >= MAX_GET) { fprintf(stderr, "fmi2_import: too many outputs\n"); return 1; }
        gvr[ng++] = (fmi2ValueReference)strtoul(argv[i], &end, 10);
        if (*end) { fprintf(stderr, "fmi2_import: bad value reference %s\n", argv[i]); return 1; }
    }

    Lib lib = lib_open(argv[1]);
    if (!lib) { fprintf(stderr, "fmi2_import: cannot load %s: %s\n", argv[1], lib_error()); return 1; }
    LOOKUP(getVersion, fmi2GetVersionTYPE *, "fmi2GetVersion")
    LOOKUP(instantiate, fmi2InstantiateTYPE *, "fmi2Instantiate")
    LOOKUP(freeInstance, fmi2FreeInstanceTYPE *, "fmi2FreeInstance")
    LOOKUP(setupExperiment, fmi2SetupExperimentTYPE *, "fmi2SetupExperiment")
    LOOKUP(enterInit, fmi2EnterInitializationModeTYPE *, "fmi2EnterInitializationMode")
    LOOKUP(exitInit, fmi2ExitInitializationModeTYPE *, "fmi2ExitInitializationMode")
    LOOKUP(terminate, fmi2TerminateTYPE *, "fmi2Terminate")
    LOOKUP(setReal, fmi2SetRealTYPE *, "fmi2SetReal")
    LOOKUP(setInteger, fmi2SetIntegerTYPE *, "fmi2SetInteger")
    LOOKUP(setBoolean, fmi2SetBooleanTYPE *, "fmi2SetBoolean")
    LOOKUP(getReal, fmi2GetRealTYPE *, "fmi2GetReal")
    LOOKUP(doStep, fmi2DoStepTYPE *, "fmi2DoStep")

    fprintf(stderr, "fmi2_import: %s, fmi2GetVersion() = %s\n", argv[1], getVersion());
    fmi2CallbackFunctions cb = {logger, calloc, free, NULL, NULL};
    fmi2Component c = instantiate("fmi2_import", fmi2CoSimulation, argv[2], "", &cb, fmi2False, fmi2False);
    if (!c) { fprintf(stderr, "fmi2_import: fmi2Instantiate returned NULL\n"); return 2; }
    /* parameters and inputs before initialisation, in the order Integer, Boolean, Real (as fmpy's
     * runner does) */
    if (ni) CHECK(setInteger(c, ivr, ni, iv));
    if (nb) CHECK(setBoolean(c, bvr, nb, bv));
    if (nr) CHECK(setReal(c, rvr, nr, rv));
    CHECK(setupExperiment(c, fmi2False, 0.0, 0.0, fmi2True, stop));
    CHECK(enterInit(c));
    CHECK(exitInit(c));
    CHECK(doStep(c, 0.0, stop, fmi2True));
    if (ng) CHECK(getReal(c, gvr, ng, gv));
    for (size_t k = 0; k < ng; k++)
        printf("%lu %016" PRIx64 " %.17g\n", (unsigned long)gvr[k], double_to_bits(gv[k]), gv[k]);
    CHECK(terminate(c));
    freeInstance(c);
    lib_close(lib);
    return 0;
}
