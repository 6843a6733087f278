/* The InterfaceElement model as the FMU runs it: its variables, the validation of its parameters, the glue
 * between the FMI layer and the equations, and the integrator of its states for co-simulation. The equations
 * are not here: they are generated from modelica/InterfaceElement.mo by fmu/codegen.py (el_generated.c,
 * described by el_model.h): the states' rates, their exact Jacobian and time derivative, and the outputs.
 *
 * Co-simulation steps integrate the states (the effects' history: Bouc-Wen yield and friction, the Maxwell
 * branch, damage) with the inputs affine in time over the step (fmi2SetRealInputDerivatives), by ROS2
 * (Verwer et al. 1999), an L-stable linearly implicit Runge-Kutta method of order 2 with the exact Jacobian
 * and an embedded order-1 solution for the error control: the Bouc-Wen and Maxwell rates are stiff where the
 * yield displacement or the relaxation time is small. */
#include "model.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

#define V(name) (mi->v[VR_##name])

static const VarInfo VARS[] = {
#define X(name, vr, type, caus, start) {name, vr, type, caus, start},
    VARIABLES(X)
#undef X
};

const VarInfo *model_variable(unsigned int vr)
{
    if (vr == 0 || vr > sizeof(VARS) / sizeof(VARS[0])) return NULL;
    return &VARS[vr - 1];
}

void model_set_start_values(ModelInstance *mi)
{
    memset(mi, 0, sizeof(*mi));
    for (size_t i = 0; i < sizeof(VARS) / sizeof(VARS[0]); i++) mi->v[VARS[i].vr] = VARS[i].start;
    mi->dirty = 1;
}

void model_free(ModelInstance *mi) { (void)mi; }

/* ------------------------------------------------------------------ validation */

static int check(int ok, char *msg, size_t len, const char *fmt, const char *name, double value)
{
    if (!ok) snprintf(msg, len, fmt, name, value);
    return !ok;
}

int model_validate(const ModelInstance *mi, char *msg, size_t len)
{
    static const char *const nonneg[] = {"c", "d", "gap", "nl_y_b", "yield_ratio", "fric_F", "ve_k", "dmg_rate",
                                         "dmg_F_res", NULL};
    static const int nonneg_vr[] = {VR_c, VR_d, VR_gap, VR_nl_y_b, VR_yield_ratio, VR_fric_F, VR_ve_k, VR_dmg_rate,
                                    VR_dmg_F_res};
    static const char *const pos[] = {"nl_ratio", "yield_F", "fric_x", "ve_tau", "smooth_w", "dmg_y0", NULL};
    static const int pos_vr[] = {VR_nl_ratio, VR_yield_F, VR_fric_x, VR_ve_tau, VR_smooth_w, VR_dmg_y0};
    for (int i = 0; nonneg[i]; i++)
        if (check(isfinite(mi->v[nonneg_vr[i]]) && mi->v[nonneg_vr[i]] >= 0.0, msg, len,
                  "parameter %s = %g is invalid: it must be finite and >= 0 (0 switches an effect off or is the "
                  "smallest value)", nonneg[i], mi->v[nonneg_vr[i]]))
            return 1;
    for (int i = 0; pos[i]; i++)
        if (check(isfinite(mi->v[pos_vr[i]]) && mi->v[pos_vr[i]] > 0.0, msg, len,
                  "parameter %s = %g is invalid: it must be a finite number > 0", pos[i], mi->v[pos_vr[i]]))
            return 1;
    if (check(V(yield_ratio) == 1.0 || V(c) > 0.0, msg, len,
              "parameter %s = %g is invalid: yield (yield_ratio != 1) needs c > 0, since the yield displacement "
              "is yield_F / c", "c", V(c)))
        return 1;
    if (check(isfinite(V(F_offset)), msg, len, "parameter %s = %g is invalid: it must be finite", "F_offset",
              V(F_offset)))
        return 1;
    if (check(isfinite(V(y_offset)), msg, len, "parameter %s = %g is invalid: it must be finite", "y_offset",
              V(y_offset)))
        return 1;
    if (check(isfinite(V(rtol)) && V(rtol) >= 1e-12 && V(rtol) <= 1e-2, msg, len,
              "parameter %s = %g is invalid: use a tolerance between 1e-12 and 1e-2", "rtol", V(rtol)))
        return 1;
    return 0;
}

/* ------------------------------------------------------------------ the generated model */

typedef int (*el_fn)(const double **arg, double **res, int *iw, double *w, int mem);

static void inputs_at(const ModelInstance *mi, double t, double *u, double *ud)
{
#define X(i, name) u[i] = mi->v[VR_##name] + mi->dv[VR_##name] * (t - mi->t_inputs); ud[i] = mi->dv[VR_##name];
    EL_INPUTS(X)
#undef X
}

static int call(ModelInstance *mi, el_fn f, double t, const double *x, double **res)
{
    double u[EL_NU], ud[EL_NU];
    inputs_at(mi, t, u, ud);
    const double *arg[EL_SZ_ARG] = {&t, x, mi->p, mi->d, u, ud};
    return f(arg, res, mi->iw, mi->w, 0);
}

static int finite_all(const double *x, int n)
{
    for (int i = 0; i < n; i++)
        if (!isfinite(x[i])) return 0;
    return 1;
}

void model_refresh(ModelInstance *mi)
{
    if (!mi->dirty) return;
    double out[EL_NOUT], dx[NX];
    double *r1[EL_SZ_RES] = {out};
    double *r2[EL_SZ_RES] = {dx};
    if (call(mi, el_full_out, mi->time, mi->x, r1) == 0) {
#define X(i, name) mi->v[VR_##name] = out[i];
        EL_OUTPUTS(X)
#undef X
    }
    if (call(mi, el_full_rhs, mi->time, mi->x, r2) == 0) {
#define X(i, name) mi->v[VR_der_##name] = dx[i];
        EL_STATE_OUTPUTS(X)
#undef X
    }
#define X(i, name) mi->v[VR_##name] = mi->x[i];
    EL_STATE_OUTPUTS(X)
#undef X
    mi->dirty = 0;
}

int model_initialize(ModelInstance *mi, double t0, char *msg, size_t len)
{
#define X(i, name) mi->p[i] = mi->v[VR_##name];
    EL_PARAMETERS(X)
#undef X
    const double *arg[EL_SZ_ARG] = {mi->p};
    double *res[EL_SZ_RES] = {mi->d};
    if (el_derived(arg, res, mi->iw, mi->w, 0)) {
        snprintf(msg, len, "the derived parameters could not be computed");
        return 1;
    }
    for (int i = 0; i < NX; i++) mi->x[i] = 0.0;    /* the effects' states start at 0 */
    /* floors of the error scale: z_y, z_f are of order 1, F_ve a force, kappa a displacement */
    mi->scale[EL_IX_z_y] = 1.0;
    mi->scale[EL_IX_z_f] = 1.0;
    mi->scale[EL_IX_F_ve] = fmax(1e-6, fabs(V(fric_F)) + fabs(V(yield_F)) * 1e-3);
    mi->scale[EL_IX_kappa] = fmax(V(smooth_w), 1e-9);
    mi->time = t0;
    mi->t_inputs = t0;
    mi->dirty = 1;
    model_refresh(mi);
    return 0;
}

void model_get_states(const ModelInstance *mi, double *x) { memcpy(x, mi->x, sizeof(mi->x)); }

void model_set_states(ModelInstance *mi, const double *x)
{
    memcpy(mi->x, x, sizeof(mi->x));
    mi->dirty = 1;
}

int model_derivatives(ModelInstance *mi, double *dx, char *msg, size_t len)
{
    double *res[EL_SZ_RES] = {dx};
    if (call(mi, el_full_rhs, mi->time, mi->x, res) || !finite_all(dx, NX)) {
        snprintf(msg, len, "the rates of the states are not finite at t = %.17g", mi->time);
        return 1;
    }
    return 0;
}

/* ------------------------------------------------------------------ co-simulation: ROS2 */

/* Solve A z = b in place (n x n, row-major), partial pivoting; 1 when singular. */
static int solve(int n, double *A, double *b)
{
    for (int k = 0; k < n; k++) {
        int p = k;
        for (int i = k + 1; i < n; i++)
            if (fabs(A[i * n + k]) > fabs(A[p * n + k])) p = i;
        if (A[p * n + k] == 0.0) return 1;
        if (p != k) {
            for (int j = 0; j < n; j++) { double t = A[k * n + j]; A[k * n + j] = A[p * n + j]; A[p * n + j] = t; }
            double t = b[k]; b[k] = b[p]; b[p] = t;
        }
        for (int i = k + 1; i < n; i++) {
            double f = A[i * n + k] / A[k * n + k];
            for (int j = k; j < n; j++) A[i * n + j] -= f * A[k * n + j];
            b[i] -= f * b[k];
        }
    }
    for (int k = n - 1; k >= 0; k--) {
        double s = b[k];
        for (int j = k + 1; j < n; j++) s -= A[k * n + j] * b[j];
        b[k] = s / A[k * n + k];
    }
    return 0;
}

#define MAX_STEPS 1000000L

int model_do_step(ModelInstance *mi, double t_end, char *msg, size_t len)
{
    const double gamma = 1.0 + 1.0 / sqrt(2.0);
    const double rtol = mi->p[EL_P_rtol];
    double t = mi->time;
    double h = t_end - t;
    long attempts = 0;
    while (t < t_end) {
        if (++attempts > MAX_STEPS) {
            snprintf(msg, len, "more than %ld integrator steps in one communication step at t = %.17g: the "
                     "effects' states are too stiff for the tolerance rtol = %g", MAX_STEPS, t, rtol);
            return 1;
        }
        if (t + h > t_end || t + 1.01 * h >= t_end) h = t_end - t;
        double f0[NX], J[NX * NX], Ft[NX], A[NX * NX], k1[NX], k2[NX], y1[NX], f1[NX];
        double *res[EL_SZ_RES] = {f0, J, Ft};
        if (call(mi, el_full_lin, t, mi->x, res) || !finite_all(f0, NX)) {
            snprintf(msg, len, "the rates of the states are not finite at t = %.17g", t);
            return 1;
        }
        for (int i = 0; i < NX; i++)
            for (int j = 0; j < NX; j++) A[i * NX + j] = (i == j ? 1.0 : 0.0) - gamma * h * J[i * NX + j];
        double A2[NX * NX];
        memcpy(A2, A, sizeof A);
        for (int i = 0; i < NX; i++) k1[i] = f0[i] + gamma * h * Ft[i];
        if (solve(NX, A, k1)) {
            snprintf(msg, len, "singular iteration matrix at t = %.17g", t);
            return 1;
        }
        for (int i = 0; i < NX; i++) y1[i] = mi->x[i] + h * k1[i];
        double *res1[EL_SZ_RES] = {f1};
        if (call(mi, el_full_rhs, t + h, y1, res1) || !finite_all(f1, NX)) {
            h *= 0.25;
            mi->n_rejected++;
            continue;
        }
        for (int i = 0; i < NX; i++) k2[i] = f1[i] - 2.0 * k1[i] - gamma * h * Ft[i];
        solve(NX, A2, k2);
        double err = 0.0, ynew[NX];
        for (int i = 0; i < NX; i++) {
            ynew[i] = mi->x[i] + 1.5 * h * k1[i] + 0.5 * h * k2[i];
            double sc = rtol * fmax(mi->scale[i], fmax(fabs(mi->x[i]), fabs(ynew[i])));
            double e = fabs(0.5 * h * (k1[i] + k2[i])) / sc;
            if (isnan(e)) err = INFINITY;   /* NaN counts as too large */
            else if (e > err) err = e;
        }
        if (err <= 1.0) {
            t += h;
            memcpy(mi->x, ynew, sizeof ynew);
            for (int i = 0; i < NX; i++) mi->scale[i] = fmax(mi->scale[i], fabs(ynew[i]));
            mi->n_steps++;
        } else {
            mi->n_rejected++;
        }
        double fac = err > 0.0 ? 0.9 / sqrt(err) : 4.0;
        h *= fmin(4.0, fmax(0.2, fac));
        if (!(h > 1e-14 * fmax(1.0, fabs(t)))) {
            snprintf(msg, len, "the step size fell below %g at t = %.17g", 1e-14 * fmax(1.0, fabs(t)), t);
            return 1;
        }
    }
    mi->time = t_end;
    mi->dirty = 1;
    model_refresh(mi);
    return 0;
}
