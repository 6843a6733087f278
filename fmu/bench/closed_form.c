/* What one axial pullout run cannot beat on this machine, timed in C without any FMI layer
 * (src/fmusa/bench.py compiles and runs it; not part of the FMU):
 *   closed_form_us: the closed-form solution of m y'' + d y' + c y = F(t) for the paper's load (ramp to
 *     F_max over t_ramp, hold to the stop time), piece by piece: the matrix exponential (phi functions)
 *     of each piece, the extrema and the start of the rest by root finding on the closed form. It runs
 *     the FMU solver's own exact-piece code on a bare 2-state right-hand side (no model, no 6-DOF state,
 *     Jacobian evaluation: J and the load are given).
 *   model_run_us: the FMU's model layer as the FMI layer drives it (start values, parameters,
 *     initialisation, one step to the stop time, outputs), without fmpy and ctypes.
 * Usage: closed_form c d F_max t_ramp stop repeats; prints JSON. */
#include "../solver.c"
#include "../model.h"

#include <stdlib.h>
#include <time.h>

typedef struct { double m, c, d, F, T; } Axial2;

static int rhs2(void *ctx, double t, const double *u, double *du, char *msg, size_t len)
{
    const Axial2 *a = ctx;
    (void)msg; (void)len;
    double F = t < a->T ? a->F * t / a->T : a->F;
    du[0] = u[1];
    du[1] = (F - a->c * u[0] - a->d * u[1]) / a->m;
    return 0;
}

static double bp2(void *ctx, double t)
{
    const Axial2 *a = ctx;
    return t < a->T ? a->T : INFINITY;
}

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

static int cmp(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* the closed form: one exact piece per load piece, J and the load slope known */
static void closed_form(Axial2 *a, double stop, double mon[3])
{
    Solver s;
    memset(&s, 0, sizeof s);
    s.n = 2; s.ipos = 0; s.ivel = 1; s.lin2 = 1; s.monitors = 1;
    s.eps_v = 5e-8; s.eps_a = 5e-9;
    s.rhs = rhs2; s.breakpoint = bp2; s.ctx = a;
    s.t_eq = 0.0;
    char msg[256];
    double t = 0.0, ends[2] = {fmin(a->T, stop), stop};
    for (int p = 0; p < 2 && t < stop; p++) {
        Linearization L;
        memset(&L, 0, sizeof L);
        L.k = 2; L.idx[0] = 0; L.idx[1] = 1; L.active[0] = L.active[1] = 1; L.t = t;
        L.J[1] = 1.0; L.J[2] = -a->c / a->m; L.J[3] = -a->d / a->m;
        L.F0[0] = s.u[1];
        L.F0[1] = p == 0 ? 0.0 : s.z[1];
        L.Ft[1] = t < a->T ? a->F / a->T / a->m : 0.0;
        memcpy(L.u, s.u, sizeof s.u);
        linear_piece(&s, &L, ends[p] - t, ends[p], msg, sizeof msg);
        t = ends[p];
    }
    mon[0] = s.pos_max; mon[1] = s.vel_max; mon[2] = s.t_eq;
}

int main(int argc, char **argv)
{
    if (argc < 7) { fprintf(stderr, "usage: closed_form c d F_max t_ramp stop repeats\n"); return 2; }
    Axial2 a = {2.9e-4, atof(argv[1]), atof(argv[2]), atof(argv[3]), atof(argv[4])};
    double stop = atof(argv[5]);
    int reps = atoi(argv[6]), inner = 50;
    double *cf = malloc(sizeof(double) * reps), *md = malloc(sizeof(double) * reps), mon[3] = {0}, sink = 0.0;
    for (int r = 0; r < reps; r++) {
        double t0 = now();
        for (int i = 0; i < inner; i++) { closed_form(&a, stop, mon); sink += mon[0]; }
        cf[r] = (now() - t0) / inner * 1e6;
    }
    static ModelInstance mi;
    char msg[512];
    double ymax = 0, vmax = 0, teq = 0;
    for (int r = 0; r < reps; r++) {
        double t0 = now();
        for (int i = 0; i < inner; i++) {
            model_set_start_values(&mi);
            mi.v[VR_c_y] = a.c; mi.v[VR_d_y] = a.d; mi.v[VR_F_max] = a.F; mi.v[VR_t_ramp] = a.T;
            if (model_validate(&mi, msg, sizeof msg) || model_initialize(&mi, 0.0, msg, sizeof msg) ||
                model_do_step(&mi, stop, msg, sizeof msg)) { fprintf(stderr, "%s\n", msg); return 1; }
            ymax = mi.v[VR_y_max]; vmax = mi.v[VR_v_y_max]; teq = mi.v[VR_t_eq];
            sink += ymax;
        }
        md[r] = (now() - t0) / inner * 1e6;
    }
    qsort(cf, reps, sizeof(double), cmp);
    qsort(md, reps, sizeof(double), cmp);
    printf("{\"closed_form_us_median\": %.6g, \"closed_form_us_min\": %.6g, \"model_run_us_median\": %.6g, "
           "\"model_run_us_min\": %.6g, \"closed_form_monitors\": [%.17g, %.17g, %.17g], "
           "\"model_monitors\": [%.17g, %.17g, %.17g], \"repeats\": %d, \"inner\": %d, \"sink\": %g}\n",
           cf[reps / 2], cf[0], md[reps / 2], md[0], mon[0], mon[1], mon[2], ymax, vmax, teq, reps, inner,
           sink * 0.0);
    return 0;
}
