/* Exponential Rosenbrock integrator with exact Jacobians (the model's, generated), active-subspace reduction,
 * dense output and the axial monitors. See solver.c for why this method. */
#ifndef SOLVER_H
#define SOLVER_H

#include <stddef.h>

#define SOLVER_NMAX 16
#define SOLVER_SMAX 8            /* forward sensitivity columns */

/* Right-hand side du = f(t, u). Returns 0 on success, nonzero (with msg filled) when the state is outside the
 * model's domain. */
typedef int (*solver_rhs_fn)(void *ctx, double t, const double *u, double *du, char *msg, size_t msglen);

/* The linearisation at (t, u), exact: du = f(t, u), the Jacobian J = d(du)/du (n x n, row-major) and the time
 * derivative Ft = d(du)/dt (with the inputs' rates). Returns as solver_rhs_fn. */
typedef int (*solver_lin_fn)(void *ctx, double t, const double *u, double *du, double *J, double *Ft, char *msg,
                             size_t msglen);

/* Forward sensitivities, column col: Fs = J S + df/dp e_col at (t, u) for S = du/dp e_col. Returns as solver_rhs_fn. */
typedef int (*solver_sens_fn)(void *ctx, int col, double t, const double *u, const double *S, double *Fs, char *msg,
                              size_t msglen);

/* The first ns columns at once: Fs[c] as solver_sens_fn's for S[c], and (Fts not NULL, where the model offers it:
 * Solver.sens_rates_given) Fts[c], its time derivative at fixed S along the states' motion. Returns as
 * solver_rhs_fn. */
typedef int (*solver_sens_all_fn)(void *ctx, int ns, double t, const double *u, const double (*S)[SOLVER_NMAX],
                                  double (*Fs)[SOLVER_NMAX], double (*Fts)[SOLVER_NMAX], char *msg, size_t msglen);

/* The same column's Fs = J S + df/dp e_col at (t, u), its Jacobian by the states at fixed S (n x n, row-major) and its
 * explicit time derivative (the inputs' rates at fixed u and S). Returns as solver_rhs_fn. */
typedef int (*solver_sens_aug_fn)(void *ctx, int col, double t, const double *u, const double *S, double *Fs,
                                  double *Fsx, double *Fst, char *msg, size_t msglen);

/* Next time > t at which the right-hand side has a kink in time (a load ramp starts or ends). */
typedef double (*solver_breakpoint_fn)(void *ctx, double t);

typedef struct {
    int n;                       /* number of states */
    int ipos, ivel;              /* monitored position and velocity (y, v_y); acceleration = du[ivel] */
    double t;
    double u[SOLVER_NMAX];
    double umax[SOLVER_NMAX];    /* running max |u_i|: the scale of the relative error control */
    double h;                    /* proposed next step */
    double rtol;                 /* local error tolerance (nonlinear part) and dense-output tolerance */
    double atol;                 /* absolute floor of the error scale: a state that starts at exactly 0 and
                                  * grows like t^k would otherwise demand a relative accuracy it cannot have */
    double h_max;                /* 0: none */
    int lin2;                    /* the model declares the (ipos, ivel) block exactly linear with a load
                                  * affine between breakpoints: such pieces are taken in one exact step */
    int monitors;                /* 0: no dense-output checks and no monitors (outputs at step ends only) */
    double eps_v, eps_a;         /* equilibrium thresholds */
    long max_steps;              /* work budget of one solver_advance: step attempts (taken or rejected) */
    double max_wall_s;           /* and seconds of computing (0: none) */
    /* monitors */
    double pos_max, vel_max, t_eq;
    double pos_int, absvel_int;  /* integrals of y and |v_y| since t0 (for the time averages) */
    double t0;
    double acc;                  /* acceleration at t (du[ivel]) */
    /* The derivative du/dt carried from step to step while the Jacobian stays the same (the linear
     * regime): recomputing it from the state would cancel F - c y in double precision and leave an
     * absolute noise of ~ulp(F)/m in the acceleration, far above the equilibrium threshold. */
    double z[SOLVER_NMAX];
    double J_prev[SOLVER_NMAX * SOLVER_NMAX];
    int z_valid;
    double bal_d[SOLVER_NMAX];   /* the balancing of the last Jacobian, by state: the next one's first guess */
    double fast_off_until;       /* the steps without dense samples are not tried before this time */
    long n_steps, n_rejected, n_rhs;
    solver_rhs_fn rhs;
    solver_lin_fn lin;
    void *work;                  /* workspace of solver_work_size() bytes, owned by the caller (NULL: the steps
                                  * without dense samples are not taken) */
    solver_breakpoint_fn breakpoint;
    void *ctx;
    /* Forward sensitivities (ns > 0): S[c] = du/dp for the parameter of column c, carried from step to step by
     * the exponential step of the linear equation S' = J(t, u(t)) S + f_p along each accepted step of the
     * states (sens_step in solver.c); they leave the states' steps unchanged. */
    int ns;
    double S[SOLVER_SMAX][SOLVER_NMAX];
    double Smax[SOLVER_SMAX][SOLVER_NMAX];   /* running max |S|: the scale of their error control */
    double sens_p[SOLVER_SMAX];  /* |p| of each column: S_i is also measured against umax_i / |p| (a state's change
                                  * for a change of p by itself) */
    double sens_rtol;            /* their local error tolerance (0: rtol; a least-squares Jacobian needs a few digits) */
    solver_sens_fn sens;         /* NULL where sens_aug is */
    solver_sens_all_fn sens_all;
    int sens_rates_given;        /* sens_all gives Fts; else the solver takes it by a forward difference */
    solver_sens_aug_fn sens_aug; /* NULL: the states' motion enters the columns only as a polynomial in time */
    /* The last sub-step of the columns, for the next one's start (sens_step in solver.c): G = J S + f_p at its end
     * for its predicted S, and G, S and J at its start. Valid only from a step's start to its end; the model clears
     * sh_valid where the inputs jump between communication steps. */
    int sh_valid;
    double sh_t0, sh_t1;
    double sh_u1[SOLVER_NMAX];
    double sh_G1[SOLVER_SMAX][SOLVER_NMAX], sh_S1[SOLVER_SMAX][SOLVER_NMAX];
    double sh_G0[SOLVER_SMAX][SOLVER_NMAX], sh_S0[SOLVER_SMAX][SOLVER_NMAX];
    double sh_J0[SOLVER_NMAX * SOLVER_NMAX];
} Solver;

/* Bytes of the workspace (Solver.work) the solver uses for the phi functions applied to vectors. */
size_t solver_work_size(void);

/* Set up at t0 with state u0; evaluates the acceleration and initialises the monitors. */
int solver_init(Solver *s, double t0, const double *u0, char *msg, size_t msglen);

/* Integrate to t_end. Returns 0 on success, 1 when a step could not be taken (msg says why). */
int solver_advance(Solver *s, double t_end, char *msg, size_t msglen);

/* phi_k(A) for k = 0..3 (phi_0 = exp), n x n row-major; exported for the unit tests. */
void solver_phi(int n, const double *A, double *P0, double *P1, double *P2, double *P3);

/* phi_k(A) x for k = 0..3 by the squaring ladder the solver uses when it needs no dense samples; exported for
 * the unit tests. */
void solver_phi_apply(int n, const double *A, const double *x, double *P0, double *P1, double *P2, double *P3);

#endif
