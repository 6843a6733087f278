/* Equations of the ScrewVertebra model: a rigid screw with 6 degrees of freedom in a fixed vertebra,
 * joined by the diagonal matrix force element of Kramer & Bauer (eq. 1). fmu/MODEL.md derives them.
 * All arithmetic on the state is complex so the solver can take exact derivatives (complex step):
 * branches look only at real parts. */
#include "model.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
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
    if (check(V(mode) == 1.0 || V(mode) == 2.0, msg, len,
              "parameter %s = %g is invalid: use 1 (force-driven) or 2 (motion-driven)", "mode", V(mode)))
        return 1;
    if (check(!(V(unload) != 0.0 && V(t_unload) < V(t_ramp)), msg, len,
              "parameter %s = %g is invalid: unloading must start after the ramp (t_unload >= t_ramp)",
              "t_unload", V(t_unload)))
        return 1;
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

/* ------------------------------------------------------------------ loads */

static cplx pull_force(const ModelInstance *mi, cplx t)
{
    double tr = creal(t), F = V(F_max), T = V(t_ramp);
    if (tr < 0.0) return 0.0;
    if (V(unload) != 0.0 && tr >= V(t_unload)) {
        if (tr >= V(t_unload) + T) return 0.0;
        return F * (1.0 - (t - V(t_unload)) / T);
    }
    if (tr < T) return F * t / T;
    return F;
}

static double next_breakpoint(void *ctx, double t)
{
    const ModelInstance *mi = ctx;
    double kinks[3] = {V(t_ramp), V(unload) != 0.0 ? V(t_unload) : INFINITY,
                       V(unload) != 0.0 ? V(t_unload) + V(t_ramp) : INFINITY};
    double next = INFINITY;
    for (int i = 0; i < 3; i++)
        if (kinks[i] > t && kinks[i] < next) next = kinks[i];
    return next;
}

static cplx input(const ModelInstance *mi, int vr, cplx t)
{
    return mi->v[vr] + mi->dv[vr] * (t - mi->t_inputs);
}

/* Axial spring force: c_y y, or the force-displacement table (linear beyond its ends). */
static cplx axial_spring(const ModelInstance *mi, cplx y)
{
    int n = (int)V(tab_n);
    if (n < 2) return V(c_y) * y;
    const double *ty = &mi->v[VR_tab_y_1], *tf = &mi->v[VR_tab_F_1];
    int k = 0;
    while (k < n - 2 && creal(y) >= ty[k + 1]) k++;
    double slope = (tf[k + 1] - tf[k]) / (ty[k + 1] - ty[k]);
    return tf[k] + slope * (y - ty[k]);
}

/* ------------------------------------------------------------------ axial effects (MODEL.md) */

/* softplus S(u) = w ln(1 + e^(u/w)) and its derivative sigma(u), overflow-free and complex-analytic */
static cplx softplus(cplx u, double w)
{
    cplx z = u / w;
    if (creal(z) > 0.0) return u + w * clog(1.0 + cexp(-z));
    return w * clog(1.0 + cexp(z));
}

static cplx sigmoid(cplx u, double w)
{
    cplx z = u / w;
    if (creal(z) >= 0.0) return 1.0 / (1.0 + cexp(-z));
    cplx e = cexp(z);
    return e / (1.0 + e);
}

/* Bouc-Wen rate with n = 4: dz/dt = (v / x_ref) (1 - H(z v) z^4) */
static cplx bouc_wen(cplx z, cplx v, cplx x_ref)
{
    cplx z2 = z * z;
    return creal(z) * creal(v) > 0.0 ? v / x_ref * (1.0 - z2 * z2) : v / x_ref;
}

typedef struct {
    cplx ye, ve;      /* elastic displacement and its rate after the gap */
    cplx spring;      /* F_s */
    cplx fric, ve_F;  /* F_f, F_ve */
    cplx damage;      /* the damage variable D in [0, 1) (0 when damage is off) */
} Axial;

/* The axial interface force F_y = F_s(y_e) + d_y v + F_f + F_ve and its parts, from the state u. */
static Axial axial_force(const ModelInstance *mi, const cplx *u)
{
    Axial a;
    cplx y = u[IX_Y], v = u[IX_VY];
    double w = V(smooth_w);
    if (V(gap) > 0.0) {
        double g = V(gap);
        a.ye = softplus(y - g, w) - softplus(-y - g, w);
        a.ve = (sigmoid(y - g, w) + sigmoid(-y - g, w)) * v;
    } else {
        a.ye = y;
        a.ve = v;
    }
    if (V(yield_ratio) != 1.0) {
        double r = V(yield_ratio);
        a.spring = r * axial_spring(mi, a.ye) + (1.0 - r) * V(yield_F) * u[IX_ZY];
    } else {
        a.spring = axial_spring(mi, a.ye);
    }
    if (V(nl_ratio) != 1.0) {
        double yb = V(nl_y_b);
        a.spring += (V(nl_ratio) - 1.0) * V(c_y) * (softplus(a.ye - yb, w) - softplus(-a.ye - yb, w));
    }
    a.damage = 0.0;
    if (V(dmg_rate) > 0.0) {
        /* interface damage: D = 1 - exp(-dmg_rate S(kappa - dmg_y0)) of the largest |y_e| reached (kappa),
         * the spring scaled by 1 - D, plus D times the residual force on the secant to the origin */
        double y0 = V(dmg_y0);
        cplx past = softplus(u[IX_KD] - y0, w);
        a.damage = 1.0 - cexp(-V(dmg_rate) * past);
        a.spring = (1.0 - a.damage) * a.spring + a.damage * V(dmg_F_res) * a.ye / (y0 + past);
    }
    a.fric = V(fric_F) > 0.0 ? V(fric_F) * u[IX_ZF] : 0.0;
    a.ve_F = V(ve_k) > 0.0 ? u[IX_FVE] : 0.0;
    return a;
}

/* Rates of the effect states; 0 for an effect that is off, so its state stays out of the active set. */
static void effect_rates(const ModelInstance *mi, const cplx *u, const Axial *a, cplx *du)
{
    cplx v = u[IX_VY];
    du[IX_ZY] = V(yield_ratio) != 1.0 ? bouc_wen(u[IX_ZY], a->ve, V(yield_F) / V(c_y)) : 0.0;
    du[IX_ZF] = V(fric_F) > 0.0 ? bouc_wen(u[IX_ZF], v, V(fric_x)) : 0.0;
    du[IX_FVE] = V(ve_k) > 0.0 ? V(ve_k) * v - u[IX_FVE] / V(ve_tau) : 0.0;
    du[IX_KD] = 0.0;
    if (V(dmg_rate) > 0.0) {
        /* kappa follows |y_e| while it grows beyond it: kappa' = max(0, sgn(y_e) v_e) sigma(|y_e| - kappa) */
        cplx sv = creal(a->ye) >= 0.0 ? a->ve : -a->ve, aye = creal(a->ye) >= 0.0 ? a->ye : -a->ye;
        if (creal(sv) > 0.0) du[IX_KD] = sv * sigmoid(aye - u[IX_KD], V(smooth_w));
    }
}

/* ------------------------------------------------------------------ small complex algebra */

/* 1/z without the range-checking complex division of libgcc: the arguments here are cos(beta) and
 * pivots, far from overflow. */
static inline cplx cinv(cplx z)
{
    double a = creal(z), b = cimag(z), d = 1.0 / (a * a + b * b);
    return a * d - I * (b * d);
}

static void mat3_vec(const cplx A[9], const cplx x[3], cplx y[3])
{
    for (int i = 0; i < 3; i++) y[i] = A[3 * i] * x[0] + A[3 * i + 1] * x[1] + A[3 * i + 2] * x[2];
}

static void mat3T_vec(const cplx A[9], const cplx x[3], cplx y[3])
{
    for (int i = 0; i < 3; i++) y[i] = A[i] * x[0] + A[3 + i] * x[1] + A[6 + i] * x[2];
}

static void mat3_mul(const cplx A[9], const cplx B[9], cplx C[9])
{
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}

static void cross(const cplx a[3], const cplx b[3], cplx c[3])
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

/* Gaussian elimination with partial pivoting on the real parts; A is n x n row-major, b overwritten. */
static int solve(int n, cplx *A, cplx *b)
{
    for (int c = 0; c < n; c++) {
        int p = c;
        for (int r = c + 1; r < n; r++)
            if (fabs(creal(A[r * n + c])) > fabs(creal(A[p * n + c]))) p = r;
        if (creal(A[p * n + c]) == 0.0) return 1;
        if (p != c) {
            for (int j = 0; j < n; j++) { cplx tmp = A[c * n + j]; A[c * n + j] = A[p * n + j]; A[p * n + j] = tmp; }
            cplx tmp = b[c]; b[c] = b[p]; b[p] = tmp;
        }
        cplx inv = cinv(A[c * n + c]);
        for (int r = c + 1; r < n; r++) {
            cplx f = A[r * n + c] * inv;
            if (f == 0.0) continue;
            for (int j = c; j < n; j++) A[r * n + j] -= f * A[c * n + j];
            b[r] -= f * b[c];
        }
    }
    for (int r = n - 1; r >= 0; r--) {
        cplx s = b[r];
        for (int j = r + 1; j < n; j++) s -= A[r * n + j] * b[j];
        b[r] = s * cinv(A[r * n + r]);
    }
    return 0;
}

/* ------------------------------------------------------------------ dynamics */

static void cos_sin(cplx x, cplx *c, cplx *s)
{
    if (x == 0.0) { *c = 1.0; *s = 0.0; return; }   /* the common axial case: skip the complex trig */
    double a = creal(x), b = cimag(x), ca = cos(a), sa = sin(a);
    if (b == 0.0) { *c = ca; *s = sa; return; }
    /* cos(a + ib) = cos a cosh b - i sin a sinh b, sin(a + ib) = sin a cosh b + i cos a sinh b; for the
     * complex step (|b| ~ 1e-100) cosh b = 1 and sinh b = b in double */
    double ch = fabs(b) < 1e-30 ? 1.0 : cosh(b), sh = fabs(b) < 1e-30 ? b : sinh(b);
    *c = ca * ch - I * (sa * sh);
    *s = sa * ch + I * (ca * sh);
}

/* Accelerations (and, in motion-driven mode, the reaction of the drive) at (t, u); ax is the axial
 * interface force of u, computed once by the caller, which also needs it for the effect states. */
static int dynamics(const ModelInstance *mi, cplx t, const cplx *u, const Axial *ax, cplx *acc, cplx *F_pull,
                    char *msg, size_t len)
{
    const cplx *q = u, *qd = u + NQ;
    cplx ca, sa, cb, sb, cg, sg;
    cos_sin(q[3], &ca, &sa);
    cos_sin(q[4], &cb, &sb);
    cos_sin(q[5], &cg, &sg);
    if (fabs(creal(cb)) < 1e-6) {
        snprintf(msg, len, "the Cardan angle beta reached %.6g rad (gimbal lock at +-pi/2): the rotational "
                 "interface stiffness c_beta or the load is unphysical", creal(q[4]));
        return 1;
    }
    /* R = Rx(alpha) Ry(beta) Rz(gamma) */
    cplx R[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    if (q[3] != 0.0 || q[4] != 0.0 || q[5] != 0.0) {
        cplx Rx[9] = {1, 0, 0, 0, ca, -sa, 0, sa, ca};
        cplx Ry[9] = {cb, 0, sb, 0, 1, 0, -sb, 0, cb};
        cplx Rz[9] = {cg, -sg, 0, sg, cg, 0, 0, 0, 1};
        cplx Rxy[9];
        mat3_mul(Rx, Ry, Rxy);
        mat3_mul(Rxy, Rz, R);
    }
    /* omega = G dtheta, dG dtheta */
    cplx G[9] = {cb * cg, sg, 0, -cb * sg, cg, 0, sb, 0, 1};
    const cplx *th = qd + 3;
    cplx w[3], Gd[3];
    mat3_vec(G, th, w);
    Gd[0] = (-sb * cg * th[1] - cb * sg * th[2]) * th[0] + cg * th[2] * th[1];
    Gd[1] = (sb * sg * th[1] - cb * cg * th[2]) * th[0] - sg * th[2] * th[1];
    Gd[2] = cb * th[1] * th[0];

    /* interface (eq. 1) */
    cplx FI[3] = {-(V(c_x) * q[0] + V(d_x) * qd[0]), -(ax->spring + V(d_y) * qd[1] + ax->fric + ax->ve_F),
                  -(V(c_z) * q[2] + V(d_z) * qd[2])};
    cplx QI[3] = {-(V(c_alpha) * q[3] + V(d_alpha) * qd[3]), -(V(c_beta) * q[4] + V(d_beta) * qd[4]),
                  -(V(c_gamma) * q[5] + V(d_gamma) * qd[5])};
    /* G^-1 in closed form (det G = cos beta); tau_I = G^-T Q_I */
    cplx icb = cinv(cb);
    cplx Gi[9] = {cg * icb, -sg * icb, 0, sg, cg, 0, -sb * cg * icb, sb * sg * icb, 1};
    cplx tauI[3];
    mat3T_vec(Gi, QI, tauI);
    /* loads at the head (without the pull, which is handled as its own column) */
    cplx FH[3] = {input(mi, VR_F_ext_x, t), input(mi, VR_F_ext_y, t), input(mi, VR_F_ext_z, t)};
    cplx TE[3] = {input(mi, VR_T_ext_x, t), input(mi, VR_T_ext_y, t), input(mi, VR_T_ext_z, t)};
    /* body vectors: b from the interaction point to the CG, h from the CG to the head */
    cplx b[3] = {V(cg_x) - V(rI_x), V(cg_y) - V(rI_y), V(cg_z) - V(rI_z)};
    cplx h[3] = {-V(cg_x), -V(cg_y), -V(cg_z)};
    cplx FIb[3], FHb[3], TEb[3], eyb[3], ey[3] = {0, 1, 0};
    mat3T_vec(R, FI, FIb);
    mat3T_vec(R, FH, FHb);
    mat3T_vec(R, TE, TEb);
    mat3T_vec(R, ey, eyb);

    cplx g[6], B[6];
    double m = V(m);
    /* translation: m r'' - m R [b]x G theta'' = F_I + F_H - m R (Gd x b + w x (w x b)) */
    cplx t1[3], t2[3], t3[3], cen[3], cenV[3];
    cross(Gd, b, t1);
    cross(w, b, t2);
    cross(w, t2, t3);
    for (int i = 0; i < 3; i++) cen[i] = t1[i] + t3[i];
    mat3_vec(R, cen, cenV);
    for (int i = 0; i < 3; i++) {
        g[i] = FI[i] + FH[i] - m * cenV[i];
        B[i] = ey[i];
    }
    /* rotation about the CG in the screw frame: I G theta'' = torques - w x I w - I Gd */
    cplx Ib[9], Iw[3], wIw[3], IGd[3], mb[3] = {-b[0], -b[1], -b[2]}, tb[3], th_[3], thy[3];
    for (int i = 0; i < 9; i++) Ib[i] = mi->inertia[i];
    mat3_vec(Ib, w, Iw);
    cross(w, Iw, wIw);
    mat3_vec(Ib, Gd, IGd);
    cross(mb, FIb, tb);
    cross(h, FHb, th_);
    cross(h, eyb, thy);
    for (int i = 0; i < 3; i++) {
        g[3 + i] = tb[i] + th_[i] + tauI[i] + TEb[i] - wIw[i] - IGd[i];
        B[3 + i] = thy[i];
    }
    if ((int)V(mode) == 2) {
        /* y'' is prescribed (u[IX_VY] carries the drive's velocity, its derivative is 0 within a step),
         * and the pull force is the unknown in its place: the full 6x6 system with that column swapped */
        cplx M[36] = {0}, bxG[9], RbxG[9], IG[9];
        for (int j = 0; j < 3; j++) {
            cplx col[3] = {G[j], G[3 + j], G[6 + j]}, c[3];
            cross(b, col, c);
            bxG[j] = c[0]; bxG[3 + j] = c[1]; bxG[6 + j] = c[2];
        }
        mat3_mul(R, bxG, RbxG);
        mat3_mul(Ib, G, IG);
        for (int i = 0; i < 3; i++) {
            M[6 * i + i] = m;
            for (int j = 0; j < 3; j++) {
                M[6 * i + 3 + j] = -m * RbxG[3 * i + j];
                M[6 * (3 + i) + 3 + j] = IG[3 * i + j];
            }
        }
        cplx ay = 0.0;
        for (int i = 0; i < 6; i++) {
            g[i] -= M[6 * i + 1] * ay;
            M[6 * i + 1] = -B[i];
        }
        if (solve(6, M, g)) goto singular;
        *F_pull = g[1];
        g[1] = ay;
    } else {
        /* M is block upper triangular: solve the rotation first, I_B (G theta'') = g_rot, then
         * r'' = g_tr / m + R (b x (G theta'')) */
        cplx Fp = pull_force(mi, t);
        for (int i = 0; i < 6; i++) g[i] += B[i] * Fp;
        cplx gr[3] = {g[3], g[4], g[5]}, wd[3], bw[3], Rbw[3], Iinv[9];
        for (int i = 0; i < 9; i++) Iinv[i] = mi->inertia_inv[i];
        mat3_vec(Iinv, gr, wd);
        mat3_vec(Gi, wd, g + 3);
        cross(b, wd, bw);
        mat3_vec(R, bw, Rbw);
        for (int i = 0; i < 3; i++) g[i] = g[i] * (1.0 / m) + Rbw[i];
        *F_pull = Fp;
    }
    for (int i = 0; i < 6; i++) acc[i] = g[i];
    return 0;
singular:
    snprintf(msg, len, "singular mass matrix: check m and the inertia (L_screw, D_screw)");
    return 1;
}

/* ------------------------------------------------------------------ Jacobian columns in closed form */

static void rmat3_vec(const double A[9], const double x[3], double y[3])
{
    for (int i = 0; i < 3; i++) y[i] = A[3 * i] * x[0] + A[3 * i + 1] * x[1] + A[3 * i + 2] * x[2];
}

static void rcross(const double a[3], const double b[3], double c[3])
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

/* The force-driven dynamics are affine in the translations and their rates (the interface force) and depend
 * on the Cardan rates only through omega = G theta', the Coriolis term G' theta' and the rotational damping:
 * those nine columns of d(du)/du are written here in closed form, from the same intermediate quantities as
 * dynamics(). A column is the mass matrix's inverse applied to the derivative of the generalised forces,
 * (g_tr, g_rot) -> (r'' = g_tr / m + R (b x wd), theta'' = G^-1 wd), wd = I^-1 g_rot. The angles' columns
 * and the time derivative stay with the complex step (tests/test_jacobian.py checks both agree). Only for the
 * linear axial element (lin2): with a table or an effect the axial force has its own derivatives. */
static int jacobian_columns(void *ctx, double t, const double *u, double *J, int *filled)
{
    const ModelInstance *mi = ctx;
    (void)t;
    if ((int)V(mode) != 1 || !mi->solver.lin2) return 0;
    enum { N = NX };
    const double *th = u + 3, *thd = u + NQ + 3;
    double ca = cos(th[0]), sa = sin(th[0]), cb = cos(th[1]), sb = sin(th[1]), cg = cos(th[2]), sg = sin(th[2]);
    if (fabs(cb) < 1e-6) return 0;   /* gimbal lock: dynamics() reports it */
    double R[9];
    {
        double Rx[9] = {1, 0, 0, 0, ca, -sa, 0, sa, ca}, Ry[9] = {cb, 0, sb, 0, 1, 0, -sb, 0, cb};
        double Rz[9] = {cg, -sg, 0, sg, cg, 0, 0, 0, 1}, Rxy[9];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                Rxy[3 * i + j] = Rx[3 * i] * Ry[j] + Rx[3 * i + 1] * Ry[3 + j] + Rx[3 * i + 2] * Ry[6 + j];
            }
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                R[3 * i + j] = Rxy[3 * i] * Rz[j] + Rxy[3 * i + 1] * Rz[3 + j] + Rxy[3 * i + 2] * Rz[6 + j];
    }
    double G[9] = {cb * cg, sg, 0, -cb * sg, cg, 0, sb, 0, 1};
    double icb = 1.0 / cb;
    double Gi[9] = {cg * icb, -sg * icb, 0, sg, cg, 0, -sb * cg * icb, sb * sg * icb, 1};
    /* dG/dbeta, dG/dgamma (dG/dalpha = 0), G' = thd_beta dG/dbeta + thd_gamma dG/dgamma */
    double Gb[9] = {-sb * cg, 0, 0, sb * sg, 0, 0, cb, 0, 0};
    double Gg[9] = {-cb * sg, cg, 0, -cb * cg, -sg, 0, 0, 0, 0};
    double Gdot[9];
    for (int i = 0; i < 9; i++) Gdot[i] = thd[1] * Gb[i] + thd[2] * Gg[i];
    double w[3], Iw[3], wb[3];
    rmat3_vec(G, thd, w);
    double b[3] = {V(cg_x) - V(rI_x), V(cg_y) - V(rI_y), V(cg_z) - V(rI_z)};
    rmat3_vec(mi->inertia, w, Iw);
    rcross(w, b, wb);
    double m = V(m);
    const double C[3] = {V(c_x), V(c_y), V(c_z)}, D[3] = {V(d_x), V(d_y), V(d_z)};
    const double Dth[3] = {V(d_alpha), V(d_beta), V(d_gamma)};
    for (int col = 0; col < 9; col++) {
        double dgt[3] = {0, 0, 0}, dgr[3] = {0, 0, 0};
        int j = col % 3, state;
        if (col < 6) {
            /* a translation (col < 3) or its rate: dF_I = -C_j e_j or -D_j e_j; torque -b x R^T dF_I */
            double k = col < 3 ? C[j] : D[j], RTe[3] = {R[3 * j], R[3 * j + 1], R[3 * j + 2]}, bx[3];
            state = col < 3 ? j : NQ + j;
            dgt[j] = -k;
            rcross(b, RTe, bx);
            for (int i = 0; i < 3; i++) dgr[i] = k * bx[i];
        } else {
            /* a Cardan rate: omega, G' theta', the damping torque G^-T (-D_j e_j), gyroscopic -w x I w */
            state = NQ + 3 + j;
            double dw[3] = {G[j], G[3 + j], G[6 + j]}, dGd[3];
            const double *Gj = j == 1 ? Gb : j == 2 ? Gg : NULL;
            for (int i = 0; i < 3; i++) {
                dGd[i] = Gdot[3 * i + j];
                if (Gj) dGd[i] += Gj[3 * i] * thd[0] + Gj[3 * i + 1] * thd[1] + Gj[3 * i + 2] * thd[2];
            }
            double t1[3], t2[3], t3[3], dwb[3], dcen[3], Rc[3];
            rcross(dGd, b, t1);
            rcross(dw, wb, t2);
            rcross(dw, b, dwb);
            rcross(w, dwb, t3);
            for (int i = 0; i < 3; i++) dcen[i] = t1[i] + t2[i] + t3[i];
            rmat3_vec(R, dcen, Rc);
            for (int i = 0; i < 3; i++) dgt[i] = -m * Rc[i];
            double Idw[3], g1[3], g2[3], IdGd[3];
            rmat3_vec(mi->inertia, dw, Idw);
            rcross(dw, Iw, g1);
            rcross(w, Idw, g2);
            rmat3_vec(mi->inertia, dGd, IdGd);
            for (int i = 0; i < 3; i++) dgr[i] = -Dth[j] * Gi[3 * j + i] - g1[i] - g2[i] - IdGd[i];
        }
        /* the inverse of the mass matrix */
        double wd[3], thdd[3], bw[3], Rbw[3];
        rmat3_vec(mi->inertia_inv, dgr, wd);
        rmat3_vec(Gi, wd, thdd);
        rcross(b, wd, bw);
        rmat3_vec(R, bw, Rbw);
        for (int i = 0; i < N; i++) J[i * N + state] = 0.0;
        if (state >= NQ) J[(state - NQ) * N + state] = 1.0;   /* dq/dt = qd */
        for (int i = 0; i < 3; i++) {
            J[(NQ + i) * N + state] = dgt[i] * (1.0 / m) + Rbw[i];
            J[(NQ + 3 + i) * N + state] = thdd[i];
        }
        filled[state] = 1;
    }
    return 0;
}

static int rhs(void *ctx, cplx t, const cplx *u, cplx *du, char *msg, size_t len)
{
    const ModelInstance *mi = ctx;
    cplx Fp;
    for (int i = 0; i < NQ; i++) du[i] = u[NQ + i];
    Axial ax = axial_force(mi, u);
    effect_rates(mi, u, &ax, du);
    return dynamics(mi, t, u, &ax, du + NQ, &Fp, msg, len);
}

/* ------------------------------------------------------------------ outputs */

static int update_outputs(ModelInstance *mi, char *msg, size_t len)
{
    cplx uc[NX], acc[NQ], Fp;
    for (int i = 0; i < NX; i++) uc[i] = mi->u[i];
    Axial ax = axial_force(mi, uc);
    if (dynamics(mi, mi->time, uc, &ax, acc, &Fp, msg, len)) return 1;
    const double *u = mi->u;
    static const int qvr[NQ] = {VR_x, VR_y, VR_z, VR_alpha, VR_beta, VR_gamma};
    static const int vvr[NQ] = {VR_v_x, VR_v_y, VR_v_z, VR_w_alpha, VR_w_beta, VR_w_gamma};
    for (int i = 0; i < NQ; i++) { mi->v[qvr[i]] = u[i]; mi->v[vvr[i]] = u[NQ + i]; }
    V(a_y) = mi->solver.acc;   /* carried by the solver: no cancellation of F - c y */
    V(F_x) = V(c_x) * u[0] + V(d_x) * u[6];
    V(F_y) = creal(ax.spring) + V(d_y) * u[IX_VY] + creal(ax.fric) + creal(ax.ve_F);
    V(F_fric) = creal(ax.fric);
    V(F_ve) = creal(ax.ve_F);
    V(dmg_D) = creal(ax.damage);
    V(y_meas) = u[IX_Y] + V(y_offset);
    V(F_z) = V(c_z) * u[2] + V(d_z) * u[8];
    V(T_alpha) = V(c_alpha) * u[3] + V(d_alpha) * u[9];
    V(T_beta) = V(c_beta) * u[4] + V(d_beta) * u[10];
    V(T_gamma) = V(c_gamma) * u[5] + V(d_gamma) * u[11];
    V(F_pull) = creal(Fp);
    V(F_meas) = creal(Fp) + V(F_offset);
    V(y_max) = mi->solver.pos_max;
    V(v_y_max) = mi->solver.vel_max;
    V(t_eq) = mi->solver.t_eq;
    {
        double span = mi->time - mi->solver.t0;
        V(y_mean) = span > 0.0 ? mi->solver.pos_int / span : u[IX_Y];
        V(v_y_mean) = span > 0.0 ? mi->solver.absvel_int / span : fabs(u[IX_VY]);
    }
    V(n_steps) = (double)mi->solver.n_steps;
    if (!mi->solver.monitors) V(y_max) = V(v_y_max) = V(y_mean) = V(v_y_mean) = V(t_eq) = NAN;
    return 0;
}

/* In motion-driven mode the drive sets y and its velocity at every communication point. */
static void apply_drive(ModelInstance *mi)
{
    if ((int)V(mode) != 2) return;
    if (V(use_y_in) != 0.0) {
        mi->u[IX_Y] = V(y_in);
        mi->u[IX_VY] = mi->dv[VR_y_in];
    } else {
        mi->u[IX_Y] = V(v_pull) * mi->time;
        mi->u[IX_VY] = V(v_pull);
    }
    mi->solver.u[IX_Y] = mi->u[IX_Y];
    mi->solver.u[IX_VY] = mi->u[IX_VY];
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
    double m = V(m), r = 0.5 * V(D_screw), L = V(L_screw);
    V(I_1) = V(I_3) = m * (3.0 * r * r + L * L) / 12.0;
    V(I_2) = 0.5 * m * r * r;
    /* I_B = Q diag(I_1, I_2, I_3) Q^T, Q = Rx(phi_inertia): principal axes of Table 1 */
    double c = cos(V(phi_inertia)), s = sin(V(phi_inertia));
    double Q[9] = {1, 0, 0, 0, c, -s, 0, s, c}, Id[3] = {V(I_1), V(I_2), V(I_3)};
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double acc = 0.0;
            for (int k = 0; k < 3; k++) acc += Q[3 * i + k] * Id[k] * Q[3 * j + k];
            mi->inertia[3 * i + j] = acc;
        }
    {   /* inverse of the symmetric positive definite I_B by cofactors */
        const double *A = mi->inertia;
        double *Ai = mi->inertia_inv;
        Ai[0] = A[4] * A[8] - A[5] * A[7];
        Ai[1] = A[2] * A[7] - A[1] * A[8];
        Ai[2] = A[1] * A[5] - A[2] * A[4];
        Ai[3] = A[5] * A[6] - A[3] * A[8];
        Ai[4] = A[0] * A[8] - A[2] * A[6];
        Ai[5] = A[2] * A[3] - A[0] * A[5];
        Ai[6] = A[3] * A[7] - A[4] * A[6];
        Ai[7] = A[1] * A[6] - A[0] * A[7];
        Ai[8] = A[0] * A[4] - A[1] * A[3];
        double det = A[0] * Ai[0] + A[1] * Ai[3] + A[2] * Ai[6];
        if (!(det > 0.0) || !isfinite(det)) {
            snprintf(msg, len, "the inertia tensor is singular: check m, L_screw and D_screw");
            return 1;
        }
        for (int i = 0; i < 9; i++) Ai[i] /= det;
    }
    mi->time = t0;
    mi->t_inputs = t0;
    memset(mi->u, 0, sizeof(mi->u));
    Solver *sv = &mi->solver;
    memset(sv, 0, sizeof(*sv));
    sv->n = NX;
    sv->ipos = IX_Y;
    sv->ivel = IX_VY;
    sv->rtol = V(rtol);
    sv->atol = 1e-15;            /* SI units: 1e-15 m, rad, m/s, rad/s: far below anything the study reads */
    sv->h_max = V(h_max);
    sv->monitors = V(monitors) != 0.0;
    sv->max_steps = (long)V(max_steps);
    sv->max_wall_s = V(max_wall_s);
    sv->lin2 = (int)V(mode) == 1 && V(tab_n) < 2.0 && V(gap) == 0.0 && V(yield_ratio) == 1.0 &&
               V(nl_ratio) == 1.0 && V(fric_F) == 0.0 && V(ve_k) == 0.0 && V(dmg_rate) == 0.0;
    sv->eps_v = V(eps_v_eq);
    sv->eps_a = V(eps_a_eq);
    sv->rhs = rhs;
    sv->columns = jacobian_columns;
    sv->breakpoint = next_breakpoint;
    sv->ctx = mi;
    sv->work = mi->work;
    apply_drive(mi);
    if (solver_init(sv, t0, mi->u, msg, len)) return 1;
    return update_outputs(mi, msg, len);
}

int model_do_step(ModelInstance *mi, double t_end, char *msg, size_t len)
{
    apply_drive(mi);
    if (solver_advance(&mi->solver, t_end, msg, len)) return 1;
    memcpy(mi->u, mi->solver.u, sizeof(mi->u));
    mi->time = t_end;
    memset(mi->dv, 0, sizeof(mi->dv));   /* input derivatives hold for one communication step */
    mi->t_inputs = t_end;
    return update_outputs(mi, msg, len);
}
