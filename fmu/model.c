/* The ScrewVertebra model as the FMU runs it: its variables, the validation of its parameters, and the glue
 * between the FMI layer, the solver and the model's equations. The equations are not here: they are
 * generated from modelica/ScrewVertebra.mo by fmu/codegen.py (sv_generated.c, described by sv_model.h):
 * the right-hand side, its exact Jacobian and time derivative, the outputs, the motion drive and the
 * load's kinks. This file only fills their argument vectors and picks the variant the parameters call for. */
#include "model.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define V(name) (mi->v[VR_##name])

#if SV_NSENS > SOLVER_SMAX
#error "fmu/generate.py SENSITIVITIES offers more parameters than the solver's SOLVER_SMAX columns"
#endif

static const VarInfo VARS[] = {
#define X(name, vr, type, caus, start) {name, vr, type, caus, start},
    VARIABLES(X)
#undef X
};

const VarInfo *model_variable(unsigned int vr)
{
    if (vr == 0 || vr > sizeof(VARS) / sizeof(VARS[0])) return NULL;
    return &VARS[vr - 1];   /* value references are the 1-based rows of the table */
}

void model_set_start_values(ModelInstance *mi)
{
    void *work = mi->work;
    memset(mi, 0, sizeof(*mi));
    mi->work = work;
    for (size_t i = 0; i < sizeof(VARS) / sizeof(VARS[0]); i++) mi->v[VARS[i].vr] = VARS[i].start;
    V(t_eq) = -1.0;
}

/* ------------------------------------------------------------------ validation */

static int check(int ok, char *msg, size_t len, const char *fmt, const char *name, double value)
{
    if (!ok) snprintf(msg, len, fmt, name, value);
    return !ok;
}

/* The entry of p of the Real parameter with value reference vr that sensitivities may be taken by; -1 for
 * another variable (an Integer or Boolean, a solver setting, not a parameter). */
static int sens_index(double vr)
{
    static const int settings[] = {VR_rtol, VR_h_max, VR_max_wall_s, VR_eps_v_eq, VR_eps_a_eq, VR_sens_rtol};
    for (size_t i = 0; i < sizeof(settings) / sizeof(settings[0]); i++)
        if (vr == settings[i]) return -1;
    const VarInfo *v = (vr >= 1.0 && vr == (double)(unsigned int)vr) ? model_variable((unsigned int)vr) : NULL;
    if (!v || v->type != TYPE_REAL || v->causality != CAUS_PARAMETER) return -1;
#define X(i, name) if (v->vr == VR_##name) return i;
    SV_PARAMETERS(X)
#undef X
    return -1;
}

int model_validate(const ModelInstance *mi, char *msg, size_t len)
{
    static const char *const nonneg[] = {"c_x", "c_y", "c_z", "c_alpha", "c_beta", "c_gamma",
                                         "d_x", "d_y", "d_z", "d_alpha", "d_beta", "d_gamma", NULL};
    static const int nonneg_vr[] = {VR_c_x, VR_c_y, VR_c_z, VR_c_alpha, VR_c_beta, VR_c_gamma,
                                    VR_d_x, VR_d_y, VR_d_z, VR_d_alpha, VR_d_beta, VR_d_gamma};
    static const char *const pos[] = {"m", "L_screw", "D_screw", "t_ramp", "eps_v_eq", "eps_a_eq", NULL};
    static const int pos_vr[] = {VR_m, VR_L_screw, VR_D_screw, VR_t_ramp, VR_eps_v_eq, VR_eps_a_eq};
    static const char *const fin[] = {"cg_x", "cg_y", "cg_z", "phi_inertia", "rI_x", "rI_y", "rI_z",
                                      "F_max", "t_unload", "v_pull", NULL};
    static const int fin_vr[] = {VR_cg_x, VR_cg_y, VR_cg_z, VR_phi_inertia, VR_rI_x, VR_rI_y, VR_rI_z,
                                 VR_F_max, VR_t_unload, VR_v_pull};
    for (int i = 0; pos[i]; i++)
        if (check(isfinite(mi->v[pos_vr[i]]) && mi->v[pos_vr[i]] > 0.0, msg, len,
                  "parameter %s = %g is invalid: it must be a finite number > 0", pos[i], mi->v[pos_vr[i]]))
            return 1;
    for (int i = 0; nonneg[i]; i++)
        if (check(isfinite(mi->v[nonneg_vr[i]]) && mi->v[nonneg_vr[i]] >= 0.0, msg, len,
                  "parameter %s = %g is invalid: stiffness and damping must be finite and >= 0",
                  nonneg[i], mi->v[nonneg_vr[i]]))
            return 1;
    for (int i = 0; fin[i]; i++)
        if (check(isfinite(mi->v[fin_vr[i]]), msg, len, "parameter %s = %g is invalid: it must be finite",
                  fin[i], mi->v[fin_vr[i]]))
            return 1;
    {   /* the axial effects (MODEL.md): every one is off at its default */
        static const char *const eff_nonneg[] = {"gap", "nl_y_b", "yield_ratio", "fric_F", "ve_k", "dmg_rate",
                                                 "dmg_F_res", NULL};
        static const int eff_nonneg_vr[] = {VR_gap, VR_nl_y_b, VR_yield_ratio, VR_fric_F, VR_ve_k, VR_dmg_rate,
                                            VR_dmg_F_res};
        static const char *const eff_pos[] = {"nl_ratio", "yield_F", "fric_x", "ve_tau", "smooth_w", "dmg_y0",
                                              NULL};
        static const int eff_pos_vr[] = {VR_nl_ratio, VR_yield_F, VR_fric_x, VR_ve_tau, VR_smooth_w, VR_dmg_y0};
        for (int i = 0; eff_nonneg[i]; i++)
            if (check(isfinite(mi->v[eff_nonneg_vr[i]]) && mi->v[eff_nonneg_vr[i]] >= 0.0, msg, len,
                      "parameter %s = %g is invalid: it must be finite and >= 0 (0 switches the effect off "
                      "or is the smallest value)", eff_nonneg[i], mi->v[eff_nonneg_vr[i]]))
                return 1;
        for (int i = 0; eff_pos[i]; i++)
            if (check(isfinite(mi->v[eff_pos_vr[i]]) && mi->v[eff_pos_vr[i]] > 0.0, msg, len,
                      "parameter %s = %g is invalid: it must be a finite number > 0", eff_pos[i],
                      mi->v[eff_pos_vr[i]]))
                return 1;
        if (check(V(yield_ratio) == 1.0 || V(c_y) > 0.0, msg, len,
                  "parameter %s = %g is invalid: yield (yield_ratio != 1) needs c_y > 0, since the yield "
                  "displacement is yield_F / c_y", "c_y", V(c_y)))
            return 1;
        if (check(isfinite(V(F_offset)), msg, len, "parameter %s = %g is invalid: it must be finite",
                  "F_offset", V(F_offset)))
            return 1;
        if (check(isfinite(V(y_offset)), msg, len, "parameter %s = %g is invalid: it must be finite",
                  "y_offset", V(y_offset)))
            return 1;
    }
    if (check(isfinite(V(rtol)) && V(rtol) >= 1e-14 && V(rtol) <= 1e-2, msg, len,
              "parameter %s = %g is invalid: use a tolerance between 1e-14 and 1e-2", "rtol", V(rtol)))
        return 1;
    if (check(isfinite(V(h_max)) && V(h_max) >= 0.0, msg, len,
              "parameter %s = %g is invalid: use 0 (no limit) or a positive step in s", "h_max", V(h_max)))
        return 1;
    if (check(V(max_steps) >= 1.0 && V(max_steps) <= 2147483647.0, msg, len,
              "parameter %s = %g is invalid: the work budget must be between 1 and 2147483647 internal steps "
              "per doStep", "max_steps", V(max_steps)))
        return 1;
    if (check(isfinite(V(max_wall_s)) && V(max_wall_s) >= 0.0, msg, len,
              "parameter %s = %g is invalid: use 0 (no limit) or a positive number of seconds", "max_wall_s",
              V(max_wall_s)))
        return 1;
    if (check(isfinite(V(sens_rtol)) && (V(sens_rtol) == 0.0 || (V(sens_rtol) >= 1e-14 && V(sens_rtol) <= 0.1)), msg,
              len, "parameter %s = %g is invalid: use 0 (the states' rtol) or a tolerance between 1e-14 and 0.1",
              "sens_rtol", V(sens_rtol)))
        return 1;
    if (check(V(mode) == 1.0 || V(mode) == 2.0, msg, len,
              "parameter %s = %g is invalid: use 1 (force-driven) or 2 (motion-driven)", "mode", V(mode)))
        return 1;
    if (check(!(V(unload) != 0.0 && V(t_unload) < V(t_ramp)), msg, len,
              "parameter %s = %g is invalid: unloading must start after the ramp (t_unload >= t_ramp)",
              "t_unload", V(t_unload)))
        return 1;
    for (int k = 0; k < SV_NSENS; k++) {   /* forward sensitivities: a Real parameter of the equations, or 0 */
        double vr = mi->v[VR_sens_p_1 + k];
        char name[16];
        snprintf(name, sizeof name, "sens_p[%d]", k + 1);
        if (vr == 0.0) continue;
        if (check(sens_index(vr) >= 0, msg, len, "parameter %s = %g is invalid: use 0 (none) or the value reference "
                  "of a Real parameter of the model's equations (not a solver setting, the mode, a switch or a "
                  "table size)", name, vr))
            return 1;
        for (int j = 0; j < k; j++)
            if (check(mi->v[VR_sens_p_1 + j] != vr, msg, len, "parameter %s = %g is invalid: another sens_p selects "
                      "the same parameter", name, vr))
                return 1;
    }
    int n = (int)V(tab_n);
    if (check(V(tab_n) == 0.0 || (V(tab_n) >= 2.0 && V(tab_n) <= 16.0 && V(tab_n) == n), msg, len,
              "parameter %s = %g is invalid: use 0 (linear c_y) or 2..16 table points", "tab_n", V(tab_n)))
        return 1;
    for (int k = 0; k < n; k++) {
        char name[16];
        double yk = mi->v[VR_tab_y_1 + k], Fk = mi->v[VR_tab_F_1 + k];
        snprintf(name, sizeof name, "tab_y[%d]", k + 1);
        if (check(isfinite(yk), msg, len, "parameter %s = %g is invalid: it must be finite", name, yk)) return 1;
        if (k > 0 && check(yk > mi->v[VR_tab_y_1 + k - 1], msg, len,
                           "parameter %s = %g is invalid: the table displacements must increase strictly "
                           "(tab_y[k] > tab_y[k-1])", name, yk))
            return 1;
        snprintf(name, sizeof name, "tab_F[%d]", k + 1);
        if (check(isfinite(Fk), msg, len, "parameter %s = %g is invalid: it must be finite", name, Fk)) return 1;
    }
    return 0;
}

/* ------------------------------------------------------------------ the generated model */

typedef int (*sv_fn)(const double **arg, double **res, int *iw, double *w, int mem);

/* The inputs at time t, extrapolated within the communication step with their derivatives, and those. */
static void inputs_at(const ModelInstance *mi, double t, double *u, double *ud)
{
#define X(i, name) u[i] = mi->v[VR_##name] + mi->dv[VR_##name] * (t - mi->t_inputs); ud[i] = mi->dv[VR_##name];
    SV_INPUTS(X)
#undef X
}

/* Call a generated function of (t, x, p, d, u, ud) with the instance's work arrays (and, for the sensitivity
 * functions, S and the direction E). */
static int call_sens(ModelInstance *mi, sv_fn f, double t, const double *x, const double *S, const double *E,
                     double **res)
{
    double u[SV_NU], ud[SV_NU];
    inputs_at(mi, t, u, ud);
    const double *arg[SV_SZ_ARG] = {&t, x, mi->p, mi->d, u, ud, S, E};
    return f(arg, res, mi->iw, mi->w, 0);
}

static int call(ModelInstance *mi, sv_fn f, double t, const double *x, double **res)
{
    return call_sens(mi, f, t, x, NULL, NULL, res);
}

static int domain(double t, const double *x, char *msg, size_t len)
{
    if (fabs(cos(x[SV_IX_beta])) < 1e-6) {
        snprintf(msg, len, "the Cardan angle beta reached %.6g rad at t = %.17g (gimbal lock at +-pi/2): the "
                 "rotational interface stiffness c_beta or the load is unphysical", x[SV_IX_beta], t);
        return 1;
    }
    return 0;
}

static int rhs(void *ctx, double t, const double *x, double *du, char *msg, size_t len)
{
    ModelInstance *mi = ctx;
    if (domain(t, x, msg, len)) return 1;
    double *res[SV_SZ_RES] = {du};
    if (call(mi, mi->f_rhs, t, x, res)) {
        snprintf(msg, len, "the generated right-hand side failed at t = %.17g", t);
        return 1;
    }
    return 0;
}

static int lin(void *ctx, double t, const double *x, double *du, double *J, double *Ft, char *msg, size_t len)
{
    ModelInstance *mi = ctx;
    if (domain(t, x, msg, len)) return 1;
    double *res[SV_SZ_RES] = {du, J, Ft};
    if (call(mi, mi->f_lin, t, x, res)) {
        snprintf(msg, len, "the generated Jacobian failed at t = %.17g", t);
        return 1;
    }
    return 0;
}

static int sens(void *ctx, int col, double t, const double *x, const double *S, double *Fs, char *msg, size_t len)
{
    ModelInstance *mi = ctx;
    if (domain(t, x, msg, len)) return 1;
    double *res[SV_SZ_RES] = {Fs};
    if (call_sens(mi, mi->f_sens_rhs, t, x, S, mi->E[col], res)) {
        snprintf(msg, len, "the generated sensitivity equations failed at t = %.17g", t);
        return 1;
    }
    return 0;
}

typedef char sens_batches_tile_E[(SV_NSENS % SV_NSENS_BATCH == 0) ? 1 : -1];   /* a batch never runs past E */

/* Every column at once, in batches of SV_NSENS_BATCH (S[c], Fs[c], Fts[c]: column c; a batch's unused columns are 0
 * in E and S); Fts only where the variant has its generated rates (force-driven). */
static int sens_all(void *ctx, int ns, double t, const double *x, const double (*S)[SOLVER_NMAX],
                    double (*Fs)[SOLVER_NMAX], double (*Fts)[SOLVER_NMAX], char *msg, size_t len)
{
    ModelInstance *mi = ctx;
    if (domain(t, x, msg, len)) return 1;
    if (Fts && !mi->f_sens_lin_all) {
        snprintf(msg, len, "internal error: the sensitivity equations' rates of this variant are not generated");
        return 1;
    }
    for (int c0 = 0; c0 < ns; c0 += SV_NSENS_BATCH) {      /* the generated functions take a batch of columns */
        int nb = ns - c0 < SV_NSENS_BATCH ? ns - c0 : SV_NSENS_BATCH;
        double SK[SV_NSENS_BATCH * NX] = {0}, FK[SV_NSENS_BATCH * NX], FtK[SV_NSENS_BATCH * NX];
        for (int b = 0; b < nb; b++) memcpy(SK + b * NX, S[c0 + b], sizeof(double) * NX);
        /* E's rows are the batch's columns as they stand (column-major np x batch), the unselected ones 0 */
        double *res[SV_SZ_RES] = {FK, Fts ? FtK : NULL};
        if (call_sens(mi, Fts ? mi->f_sens_lin_all : mi->f_sens_rhs_all, t, x, SK, mi->E[c0], res)) {
            snprintf(msg, len, "the generated sensitivity equations failed at t = %.17g", t);
            return 1;
        }
        for (int b = 0; b < nb; b++) {
            memcpy(Fs[c0 + b], FK + b * NX, sizeof(double) * NX);
            if (Fts) memcpy(Fts[c0 + b], FtK + b * NX, sizeof(double) * NX);
        }
    }
    return 0;
}

static int sens_aug(void *ctx, int col, double t, const double *x, const double *S, double *Fs, double *Fsx,
                    double *Fst, char *msg, size_t len)
{
    ModelInstance *mi = ctx;
    if (domain(t, x, msg, len)) return 1;
    double *res[SV_SZ_RES] = {Fs, Fsx, Fst};
    if (call_sens(mi, mi->f_sens_aug, t, x, S, mi->E[col], res)) {
        snprintf(msg, len, "the generated sensitivity equations failed at t = %.17g", t);
        return 1;
    }
    return 0;
}

static double next_breakpoint(void *ctx, double t)
{
    const ModelInstance *mi = ctx;
    double next = INFINITY;
    for (int i = 0; i < SV_NKINKS; i++)
        if (mi->kinks[i] > t && mi->kinks[i] < next) next = mi->kinks[i];
    return next;
}

/* ------------------------------------------------------------------ outputs */

static int update_outputs(ModelInstance *mi, char *msg, size_t len)
{
    const double *u = mi->u;
    double out[SV_NOUT];
    if (domain(mi->time, u, msg, len)) return 1;
    double *res[SV_SZ_RES] = {out};
    if (call(mi, mi->f_out, mi->time, u, res)) {
        snprintf(msg, len, "the generated outputs failed at t = %.17g", mi->time);
        return 1;
    }
#define X(i, name) V(name) = u[i];
    SV_STATE_OUTPUTS(X)
#undef X
#define X(i, name) V(name) = out[i];
    SV_OUTPUTS(X)
#undef X
    for (int i = 0; i < SV_NOUT; i++)
        if (!isfinite(out[i])) {
            snprintf(msg, len, "the outputs are not finite at t = %.17g", mi->time);
            return 1;
        }
    V(a_y) = mi->solver.acc;   /* carried by the solver: no cancellation of F - c y */
    V(y_max) = mi->solver.pos_max;
    V(v_y_max) = mi->solver.vel_max;
    V(t_eq) = mi->solver.t_eq;
    {
        double span = mi->time - mi->solver.t0;
        V(y_mean) = span > 0.0 ? mi->solver.pos_int / span : u[SV_IX_POSITION];
        V(v_y_mean) = span > 0.0 ? mi->solver.absvel_int / span : fabs(u[SV_IX_VELOCITY]);
    }
    V(n_steps) = (double)mi->solver.n_steps;
    for (int c = 0; c < mi->n_sens; c++) {
        double dout[SV_NSENS_OUT];
        double *rs[SV_SZ_RES] = {dout};
        if (call_sens(mi, mi->f_sens_out, mi->time, u, mi->solver.S[c], mi->E[c], rs)) {
            snprintf(msg, len, "the generated output sensitivities failed at t = %.17g", mi->time);
            return 1;
        }
#define X(i, name) mi->v[VR_sens_##name##_1 + mi->sens_col[c]] = dout[i];
        SV_SENS_OUTPUTS(X)
#undef X
    }
    if (!mi->solver.monitors) V(y_max) = V(v_y_max) = V(y_mean) = V(v_y_mean) = V(t_eq) = NAN;
    return 0;
}

/* In motion-driven mode the drive sets the states it prescribes at every communication point. */
static int apply_drive(ModelInstance *mi, char *msg, size_t len)
{
    if (!mi->f_drive) return 0;
    double u[SV_NU], ud[SV_NU], xd[SV_NDRIVE], t = mi->time;
    inputs_at(mi, t, u, ud);
    const double *arg[SV_SZ_ARG] = {&t, mi->p, mi->d, u, ud};
    double *res[SV_SZ_RES] = {xd};
    if (mi->f_drive(arg, res, mi->iw, mi->w, 0)) {
        snprintf(msg, len, "the generated drive failed at t = %.17g", t);
        return 1;
    }
#define X(i, name) mi->u[SV_IX_##name] = mi->solver.u[SV_IX_##name] = xd[i];
    SV_DRIVE(X)
#undef X
    for (int c = 0; c < mi->n_sens; c++) {   /* the prescribed states' sensitivities */
        arg[5] = mi->E[c];
        if (mi->f_sens_drive(arg, res, mi->iw, mi->w, 0)) {
            snprintf(msg, len, "the generated drive sensitivities failed at t = %.17g", t);
            return 1;
        }
#define X(i, name) mi->solver.S[c][SV_IX_##name] = xd[i];
        SV_DRIVE(X)
#undef X
    }
    return 0;
}

void model_free(ModelInstance *mi)
{
    free(mi->work);
    mi->work = NULL;
}

int model_initialize(ModelInstance *mi, double t0, char *msg, size_t len)
{
    if (!mi->work && !(mi->work = calloc(1, solver_work_size()))) {
        snprintf(msg, len, "out of memory: the solver's workspace (%lu bytes) could not be allocated",
                 (unsigned long)solver_work_size());
        return 1;
    }
#define X(i, name) mi->p[i] = V(name);
    SV_PARAMETERS(X)
#undef X
    {   /* the derived parameters, once */
        const double *arg[SV_SZ_ARG] = {mi->p};
        double *res[SV_SZ_RES] = {mi->d};
        if (sv_derived(arg, res, mi->iw, mi->w, 0)) {
            snprintf(msg, len, "the generated derived parameters failed");
            return 1;
        }
        /* (a derived parameter of an effect that is off may be infinite, yield_F / c_y at c_y = 0: unused) */
        if (!(mi->d[SV_D_I_det] > 0.0) || !isfinite(mi->d[SV_D_I_det])) {
            snprintf(msg, len, "the inertia tensor is singular: check m, L_screw and D_screw");
            return 1;
        }
        arg[0] = mi->p;
        arg[1] = mi->d;
        res[0] = mi->kinks;
        if (sv_kinks(arg, res, mi->iw, mi->w, 0)) {
            snprintf(msg, len, "the generated kinks of the load failed");
            return 1;
        }
    }
#define X(i, name) V(name) = mi->d[i];
    SV_CALCULATED(X)
#undef X
    /* the variant: force-driven with every effect off (core), force-driven, motion-driven (fmu/codegen.py) */
    /* forward sensitivities: the selected parameters, in the order of sens_p (fmu/generate.py SENSITIVITIES) */
    double p_abs[SV_NSENS];
    mi->n_sens = 0;
    memset(mi->E, 0, sizeof(mi->E));
    for (int k = 0; k < SV_NSENS; k++) {
        int i = mi->v[VR_sens_p_1 + k] != 0.0 ? sens_index(mi->v[VR_sens_p_1 + k]) : -1;
        if (i < 0) continue;
        mi->E[mi->n_sens][i] = 1.0;
        p_abs[mi->n_sens] = fabs(mi->p[i]);
        mi->sens_col[mi->n_sens++] = k;
    }
    for (int k = 0; k < SV_NSENS; k++) {
#define X(i, name) mi->v[VR_sens_##name##_1 + k] = 0.0;
        SV_SENS_OUTPUTS(X)
#undef X
    }
    /* the variant: force-driven with every effect off (core), force-driven, motion-driven (fmu/codegen.py);
     * sensitivities take the full one (a core variant holds the effects' parameters fixed) */
    int motion = (int)V(mode) == SV_MODE_MOTION, core = !motion && !mi->n_sens && SV_IS_CORE(mi->p);
    mi->f_rhs = motion ? sv_motion_full_rhs : core ? sv_force_core_rhs : sv_force_full_rhs;
    mi->f_lin = motion ? sv_motion_full_lin : core ? sv_force_core_lin : sv_force_full_lin;
    mi->f_out = motion ? sv_motion_full_out : core ? sv_force_core_out : sv_force_full_out;
    mi->f_drive = motion ? sv_motion_full_drive : NULL;
    /* a prescribed motion does not ring: no column steps with the states, and the sensitivity equations' rates are
     * the solver's difference (fmu/codegen.py generates neither for it) */
    mi->f_sens_rhs = motion ? NULL : sv_force_full_sens_rhs;
    mi->f_sens_aug = motion ? NULL : sv_force_full_sens_aug;
    mi->f_sens_lin_all = motion ? NULL : sv_force_full_sens_lin_all;
    mi->f_sens_rhs_all = motion ? sv_motion_full_sens_rhs_all : sv_force_full_sens_rhs_all;
    mi->f_sens_out = motion ? sv_motion_full_sens_out : sv_force_full_sens_out;
    mi->f_sens_drive = motion ? sv_motion_full_sens_drive : NULL;
    mi->time = t0;
    mi->t_inputs = t0;
    memset(mi->u, 0, sizeof(mi->u));   /* at rest in the reference configuration (the Modelica's initial equations) */
    mi->inputs_end_valid = 0;
    Solver *sv = &mi->solver;
    memset(sv, 0, sizeof(*sv));
    sv->n = NX;
    sv->ipos = SV_IX_POSITION;
    sv->ivel = SV_IX_VELOCITY;
    sv->rtol = V(rtol);
    sv->sens_rtol = V(sens_rtol) > 0.0 ? V(sens_rtol) : V(rtol);
    sv->atol = 1e-15;            /* SI units: 1e-15 m, rad, m/s, rad/s: far below anything the study reads */
    sv->h_max = V(h_max);
    sv->monitors = V(monitors) != 0.0;
    sv->max_steps = (long)V(max_steps);
    sv->max_wall_s = V(max_wall_s);
    /* the exact axial steps: the core force-driven variant, whose axial block fmu/codegen.py proves linear */
    sv->lin2 = core;
    sv->eps_v = V(eps_v_eq);
    sv->eps_a = V(eps_a_eq);
    sv->rhs = rhs;
    sv->lin = lin;
    sv->breakpoint = next_breakpoint;
    sv->ns = mi->n_sens;
    sv->sens = mi->f_sens_rhs ? sens : NULL;
    sv->sens_aug = mi->f_sens_aug ? sens_aug : NULL;
    sv->sens_all = sens_all;
    sv->sens_rates_given = mi->f_sens_lin_all != NULL;
    for (int c = 0; c < mi->n_sens; c++) sv->sens_p[c] = p_abs[c];
    sv->ctx = mi;
    sv->work = mi->work;
    if (apply_drive(mi, msg, len)) return 1;
    if (solver_init(sv, t0, mi->u, msg, len)) return 1;
    return update_outputs(mi, msg, len);
}

int model_do_step(ModelInstance *mi, double t_end, char *msg, size_t len)
{
    double u[SV_NU], ud[SV_NU];
    if (mi->inputs_end_valid) {
        /* the sensitivities' last sub-step holds at the next step's start (Solver.sh_valid) only where the inputs
         * go on from the values the last communication step ended with */
        inputs_at(mi, mi->time, u, ud);
        for (int i = 0; i < SV_NU; i++)
            if (fabs(u[i] - mi->inputs_end[i]) > 1e-12 * (fabs(u[i]) + fabs(mi->inputs_end[i])))
                mi->solver.sh_valid = 0;
    }
    if (apply_drive(mi, msg, len)) return 1;
    if (solver_advance(&mi->solver, t_end, msg, len)) return 1;
    inputs_at(mi, t_end, mi->inputs_end, ud);
    mi->inputs_end_valid = 1;
    memcpy(mi->u, mi->solver.u, sizeof(mi->u));
    mi->time = t_end;
    memset(mi->dv, 0, sizeof(mi->dv));   /* input derivatives hold for one communication step */
    mi->t_inputs = t_end;
    return update_outputs(mi, msg, len);
}
