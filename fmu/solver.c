/* The solver of the ScrewVertebra FMU.
 *
 * Why this method. The paper's parameter range, c up to 6.1e9 N/m and d up to 2.44e8 N s/m on a 0.29 g
 * screw, puts eigenvalues anywhere from -1e12 1/s to ~0 and undamped frequencies up to 5e6 rad/s, while a
 * pullout lasts seconds. An explicit method would need 1e12 steps; an implicit one with error control is
 * stable but damps or dephases a d = 0 oscillation over thousands of periods. We use an exponential
 * Rosenbrock method (exprb32, Hochbruck, Ostermann & Schweitzer 2009):
 *     U     = u + h phi1(hJ) F(u) + h^2 phi2(hJ) F_t
 *     u_new = U + 2h phi3(hJ) D,  D = F(U) - F(u) - J (U - u) - h F_t,
 * with J = dF/du and F_t = dF/dt exact: the model gives them (Solver.lin: code generated from the Modelica
 * source with its symbolic derivatives, fmu/codegen.py). For a linear element with a
 * piecewise-linear load (the paper's case) D vanishes and a step is exact to rounding whatever its length,
 * at any stiffness, without numerical damping; for the nonlinear 6-DOF dynamics (gyroscopic terms, finite
 * rotations, lever arms, a force table) the method is third order, A-stable through the exact exponential,
 * and D gives the error estimate. Steps never cross a load kink.
 *
 * The phi functions come from scaling, a Taylor series and the doubling formula
 *     phi_k(2z) = 2^-k [ phi_0(z) phi_k(z) + sum_{j=1..k} phi_j(z)/(k-j)! ],
 * after a diagonal balancing that makes stiff blocks well conditioned.
 *
 * Only the active subspace is integrated: states that are zero, have zero derivative and are not driven by
 * any active state stay exactly zero. The axial pullout thus costs 2x2 algebra even in the 12-state model.
 *
 * The monitors need the solution between steps. Where the model declares the (y, v_y) block linear
 * (Solver.lin2) but other states move (the 6-DOF load case), that block is a damped oscillator forced by the
 * load and by its (small) coupling to the rest: each step's monitors come from the oscillator's closed form
 * with an affine forcing through both ends of the step, which must reproduce the integrator's end to the local
 * tolerance rtol (fast_step), and the phi functions are applied to vectors by a squaring ladder: the step is
 * set by the error estimate alone, no dense samples. Otherwise (a table, an effect, motion-driven) each step
 * is sampled at 8 sub-points by propagating the linearised dynamics exactly (the same phi functions at h/8),
 * and a step is accepted only when every odd sample agrees with the cubic Hermite interpolant of its
 * neighbours to min(1e-7, 100 rtol), so no oscillation hides between samples. Peaks come from those cubics,
 * and the start of the equilibrium (t_eq) is located by root finding on the exact linearised solution, not
 * rounded to a step. With monitors = false neither is needed and the steps take the ladder.
 *
 * Work budget: one solver_advance stops with an error after max_steps step attempts or max_wall_s seconds.
 *
 * Exact pieces. When the model declares the (y, v_y) block exactly linear (Solver.lin2: force-driven, no
 * table, no effect) and the active set is that block alone (the axial pullout), a load piece (between two
 * kinks, or to the end of the communication step) is taken in ONE step: the end state from the phi
 * functions of the 2x2 block, and the monitors from the closed form of the damped oscillator on the piece
 * (linear_piece below): max |y| at the roots of v, max |v| at the closed-form zeros of a, the integrals of y
 * and |v| exactly, and t_eq as the last crossing of |v| = eps_v or |a| = eps_a, found with the geometric
 * decay of the oscillation's extrema and a safeguarded Newton iteration on the closed form. A piece that
 * would need more than PIECE_MAX_ROOTS roots goes to the general stepper. */
#if !defined(_WIN32) && !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 199309L   /* clock_gettime */
#endif
#include "solver.h"

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#ifdef _WIN32
#include <windows.h>
#else
#include <time.h>
#endif

#define NMAX SOLVER_NMAX
#define NSUB 8                 /* dense samples per step */

/* ---------------------------------------------------------------- small dense linear algebra */

/* C = A B. The i-k-j order runs the inner loop over contiguous rows (vectorised) and adds the products
 * in the same order as the dot product k = 0..n-1, so the result is bit for bit that of the i-j-k loop. */
static inline __attribute__((always_inline)) void matmul_n(int n, const double *restrict A, const double *restrict B, double *restrict C)
{
    for (int i = 0; i < n; i++) {
        double *c = C + i * n;
        for (int j = 0; j < n; j++) c[j] = 0.0;
        for (int k = 0; k < n; k++) {
            double a = A[i * n + k];
            const double *b = B + k * n;
            for (int j = 0; j < n; j++) c[j] += a * b[j];
        }
    }
}

/* T1 = E P1, T2 = E P2, T3 = E P3, T0 = E E in one pass over E (same summation order as matmul). */
static inline __attribute__((always_inline)) void matmul4_n(int n, const double *restrict E, const double *restrict P1,
                             const double *restrict P2, const double *restrict P3, double *restrict T0,
                             double *restrict T1, double *restrict T2, double *restrict T3)
{
    for (int i = 0; i < n; i++) {
        double *c0 = T0 + i * n, *c1 = T1 + i * n, *c2 = T2 + i * n, *c3 = T3 + i * n;
        for (int j = 0; j < n; j++) c0[j] = c1[j] = c2[j] = c3[j] = 0.0;
        for (int k = 0; k < n; k++) {
            double a = E[i * n + k];
            const double *b0 = E + k * n, *b1 = P1 + k * n, *b2 = P2 + k * n, *b3 = P3 + k * n;
            for (int j = 0; j < n; j++) {
                c0[j] += a * b0[j];
                c1[j] += a * b1[j];
                c2[j] += a * b2[j];
                c3[j] += a * b3[j];
            }
        }
    }
}

/* Fixed-size kernels: the block sizes of the screw (2, 4, 6, 10, 12 states) get loops of constant
 * length that the compiler unrolls and vectorises. With GCC on x86-64 Linux they are also built for AVX2 with
 * FMA and chosen at load time (ifunc), falling back to the baseline SSE2 code elsewhere. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && !defined(SOLVER_NO_CLONES)
#define KERNEL __attribute__((target_clones("fma", "default"), optimize("fp-contract=fast")))
#else
#define KERNEL
#endif
#define FIXED_SIZES(CALL) \
    switch (n) { \
    case 2: CALL(2); break; case 4: CALL(4); break; case 6: CALL(6); break; case 8: CALL(8); break; \
    case 10: CALL(10); break; case 12: CALL(12); break; default: CALL(n); break; }

KERNEL static void matmul(int n, const double *restrict A, const double *restrict B, double *restrict C)
{
#define MM(N) matmul_n(N, A, B, C)
    FIXED_SIZES(MM)
#undef MM
}

KERNEL static void matmul4(int n, const double *restrict E, const double *restrict P1, const double *restrict P2,
                    const double *restrict P3, double *restrict T0, double *restrict T1, double *restrict T2,
                    double *restrict T3)
{
#define MM4(N) matmul4_n(N, E, P1, P2, P3, T0, T1, T2, T3)
    FIXED_SIZES(MM4)
#undef MM4
}

static void matvec(int n, const double *A, const double *x, double *y)
{
    for (int i = 0; i < n; i++) {
        double s = 0.0;
        for (int k = 0; k < n; k++) s += A[i * n + k] * x[k];
        y[i] = s;
    }
}

/* y = A x from the transpose AT = A^T: a sum of contiguous rows of AT, each lane its own sum (vectorises
 * without reordering additions). */
static inline __attribute__((always_inline)) void matvec_t_n(int n, const double *restrict AT, const double *restrict x, double *restrict y)
{
    for (int j = 0; j < n; j++) y[j] = 0.0;
    for (int k = 0; k < n; k++) {
        double a = x[k];
        const double *r = AT + k * n;
        for (int j = 0; j < n; j++) y[j] += a * r[j];
    }
}

KERNEL static void matvec_t(int n, const double *restrict AT, const double *restrict x, double *restrict y)
{
#define MV(N) matvec_t_n(N, AT, x, y)
    FIXED_SIZES(MV)
#undef MV
}

/* Parlett-Reinsch balancing with powers of two (exact): B = D^-1 A D, from d = 1. */
static void balance_sweeps(int n, double *B, double *d);

static void balance(int n, double *B, double *d)
{
    for (int i = 0; i < n; i++) d[i] = 1.0;
    balance_sweeps(n, B, d);
}

/* The same from a guess d (powers of two, e.g. the balancing of the last step's Jacobian): B = D^-1 A D with
 * A given in B; a guess close to the answer leaves one or two sweeps. */
static void balance_from(int n, double *B, double *d)
{
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) B[i * n + j] = B[i * n + j] * (d[j] / d[i]);
    balance_sweeps(n, B, d);
}

static void balance_sweeps(int n, double *B, double *d)
{
    for (int sweep = 0; sweep < 64; sweep++) {
        int done = 1;
        for (int i = 0; i < n; i++) {
            double c = 0.0, r = 0.0;
            for (int j = 0; j < n; j++)
                if (j != i) { c += fabs(B[j * n + i]); r += fabs(B[i * n + j]); }
            if (c == 0.0 || r == 0.0) continue;
            double g = r / 2.0, f = 1.0, s = c + r;
            while (c < g) { f *= 2.0; c *= 4.0; }
            g = r * 2.0;
            while (c > g) { f /= 2.0; c /= 4.0; }
            if ((c + r) / f < 0.95 * s) {
                done = 0;
                d[i] *= f;
                for (int j = 0; j < n; j++) B[i * n + j] /= f;
                for (int j = 0; j < n; j++) B[j * n + i] *= f;
            }
        }
        if (done) break;
    }
}

/* One application of the doubling formula, phi_k(2z) from phi_k(z), written in E = phi_0 - I:
 *   E' = 2E + E^2, phi1' = phi1 + E phi1 / 2, phi2' = (2 phi2 + E phi2 + phi1) / 4,
 *   phi3' = (2 phi3 + E phi3 + phi1 / 2 + phi2) / 8.
 * Carrying E instead of exp keeps slow modes: with 40 doublings exp(z / 2^40) of a slow eigenvalue
 * rounds to 1, but E keeps its relative precision (the expm1 idea). */
static void phi_double(int n, double *E, double *P1, double *P2, double *P3)
{
    double T0[NMAX * NMAX], T1[NMAX * NMAX], T2[NMAX * NMAX], T3[NMAX * NMAX];
    int nn = n * n;
    matmul4(n, E, P1, P2, P3, T0, T1, T2, T3);
    for (int i = 0; i < nn; i++) {
        double p1 = P1[i], p2 = P2[i], p3 = P3[i];
        E[i] = 2.0 * E[i] + T0[i];
        P1[i] = p1 + 0.5 * T1[i];
        P2[i] = 0.25 * (2.0 * p2 + T2[i] + p1);
        P3[i] = 0.125 * (2.0 * p3 + T3[i] + 0.5 * p1 + p2);
    }
}

static void add_identity(int n, double *P)
{
    for (int i = 0; i < n; i++) P[i * n + i] += 1.0;
}

/* phi_1..3 and E = phi_0 - I of a balanced matrix B / 2^s by Taylor series (||B/2^s||_1 <= 1/2, 14 terms:
 * < 1e-19). */
static int phi_taylor(int n, const double *B, double *P0, double *P1, double *P2, double *P3)
{
    double norm = 0.0;
    for (int j = 0; j < n; j++) {
        double c = 0.0;
        for (int i = 0; i < n; i++) c += fabs(B[i * n + j]);
        if (c > norm) norm = c;
    }
    int s = 0;
    if (norm > 0.5) s = (int)ceil(log2(norm / 0.5));
    double scale = ldexp(1.0, -s);
    double Z[NMAX * NMAX], T[NMAX * NMAX];
    int nn = n * n;
    for (int i = 0; i < nn; i++) Z[i] = B[i] * scale;
    /* Horner for phi3 = sum_i Z^i / (i+3)! */
    enum { NT = 14 };
    double fact[NT + 4];
    fact[0] = 1.0;
    for (int i = 1; i < NT + 4; i++) fact[i] = fact[i - 1] * i;
    for (int i = 0; i < nn; i++) P3[i] = 0.0;
    for (int i = 0; i < n; i++) P3[i * n + i] = 1.0 / fact[NT + 3];
    for (int k = NT - 1; k >= 0; k--) {
        matmul(n, Z, P3, T);
        memcpy(P3, T, sizeof(double) * nn);
        for (int i = 0; i < n; i++) P3[i * n + i] += 1.0 / fact[k + 3];
    }
    matmul(n, Z, P3, P2);
    for (int i = 0; i < n; i++) P2[i * n + i] += 0.5;
    matmul(n, Z, P2, P1);
    for (int i = 0; i < n; i++) P1[i * n + i] += 1.0;
    matmul(n, Z, P1, P0);   /* E = phi_0 - I; the caller adds I after the doublings */
    return s;
}

static void unbalance(int n, const double *d, double *P)
{
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) P[i * n + j] *= d[i] / d[j];
}

/* phi_k(A/8) (the sub-step) and phi_k(A) (the step), k = 0..3, of one dense block. */
static void phi_pair_dense(int n, const double *A, double sub[4][NMAX * NMAX], double full[4][NMAX * NMAX])
{
    double B[NMAX * NMAX], d[NMAX];
    int nn = n * n;
    memcpy(B, A, sizeof(double) * nn);
    balance(n, B, d);
    for (int i = 0; i < nn; i++) B[i] *= 1.0 / NSUB;
    int s = phi_taylor(n, B, sub[0], sub[1], sub[2], sub[3]);
    for (int i = 0; i < s; i++) phi_double(n, sub[0], sub[1], sub[2], sub[3]);
    for (int k = 0; k < 4; k++) memcpy(full[k], sub[k], sizeof(double) * nn);
    for (int i = 0; i < 3; i++) phi_double(n, full[0], full[1], full[2], full[3]); /* 8 = 2^3 */
    add_identity(n, sub[0]);
    add_identity(n, full[0]);
    for (int k = 0; k < 4; k++) { unbalance(n, d, sub[k]); unbalance(n, d, full[k]); }
}

/* Connected components of the coupling graph of A: matrix functions of a block-diagonal matrix are
 * block diagonal, and the cost is cubic in the block size (the 6-DOF screw splits into 2+2+2+6). */
static int components(int n, const double *A, int *label)
{
    int nc = 0;
    for (int i = 0; i < n; i++) label[i] = -1;
    for (int i = 0; i < n; i++) {
        if (label[i] >= 0) continue;
        int stack[NMAX], top = 0;
        label[i] = nc;
        stack[top++] = i;
        while (top) {
            int a = stack[--top];
            for (int b = 0; b < n; b++)
                if (label[b] < 0 && (A[a * n + b] != 0.0 || A[b * n + a] != 0.0)) {
                    label[b] = nc;
                    stack[top++] = b;
                }
        }
        nc++;
    }
    return nc;
}

static void phi_pair(int n, const double *A, double sub[4][NMAX * NMAX], double full[4][NMAX * NMAX])
{
    int label[NMAX], nc = components(n, A, label);
    if (nc == 1) { phi_pair_dense(n, A, sub, full); return; }
    for (int k = 0; k < 4; k++) {
        memset(sub[k], 0, sizeof(double) * n * n);
        memset(full[k], 0, sizeof(double) * n * n);
    }
    for (int c = 0; c < nc; c++) {
        int idx[NMAX], m = 0;
        for (int i = 0; i < n; i++)
            if (label[i] == c) idx[m++] = i;
        double Am[NMAX * NMAX], sm[4][NMAX * NMAX], fm[4][NMAX * NMAX];
        for (int a = 0; a < m; a++)
            for (int b = 0; b < m; b++) Am[a * m + b] = A[idx[a] * n + idx[b]];
        phi_pair_dense(m, Am, sm, fm);
        for (int k = 0; k < 4; k++)
            for (int a = 0; a < m; a++)
                for (int b = 0; b < m; b++) {
                    sub[k][idx[a] * n + idx[b]] = sm[k][a * m + b];
                    full[k][idx[a] * n + idx[b]] = fm[k][a * m + b];
                }
    }
}

void solver_phi(int n, const double *A, double *P0, double *P1, double *P2, double *P3)
{
    double B[NMAX * NMAX], d[NMAX];
    memcpy(B, A, sizeof(double) * n * n);
    balance(n, B, d);
    int s = phi_taylor(n, B, P0, P1, P2, P3);
    for (int i = 0; i < s; i++) phi_double(n, P0, P1, P2, P3);
    add_identity(n, P0);
    unbalance(n, d, P0); unbalance(n, d, P1); unbalance(n, d, P2); unbalance(n, d, P3);
}

/* ---------------------------------------------------------------- phi functions applied to vectors
 *
 * A step that needs no dense samples needs phi_k(A) only applied to three vectors (phi1 F0, phi2 Ft, phi3 D),
 * not the matrices. The ladder keeps the matrices E_j = expm1(2^j Z), Z = B / 2^s, j = 0..s, of the balanced
 * B = D^-1 A D: one squaring per level, E_{j+1} = 2 E_j + E_j^2 (a quarter of the work of doubling all four
 * phi functions), and a vector climbs the ladder with the doubling formulas of phi_double applied to it:
 *   p1' = p1 + E p1 / 2,  p2' = (2 p2 + E p2 + p1) / 4,  p3' = (2 p3 + E p3 + p1 / 2 + p2) / 8,
 * from phi_k(Z) x by a Taylor series at the bottom; phi_0(A) x = x + E_s x at the top. The recurrences are
 * those of the matrix doubling applied to one vector, so the accuracy is the same (tests/test_solver_phi.py).
 * The ladder holds the transposes (E_j^T = expm1(2^j Z^T)), so that E_j x is a sum of contiguous rows
 * (matvec_t) that vectorises without reordering any sum. Matrix functions of a block-diagonal matrix are
 * block diagonal: each coupled component gets its own ladder. */

#define LADDER_LEVELS 64          /* squarings a ladder can hold: ||B||_1 up to 2^63 */
#define LADDER_BUF ((LADDER_LEVELS + 3) * NMAX * NMAX)

typedef struct {
    int n, s;
    int idx[NMAX];                /* the component's rows in the block */
    double d[NMAX];               /* balancing: Jb = D^-1 J D of the component */
    double Jb[NMAX * NMAX];       /* the balanced block of J itself (h = 1): hJ balances to h Jb exactly */
    const double *ZT;             /* (h Jb / 2^s)^T */
    const double *P1T;            /* phi1(Z)^T, the bottom of the F0 pass */
    const double *ET;             /* E_0^T .. E_s^T, n * n each */
} Ladder;

typedef struct {
    int k, nc;
    Ladder lad[NMAX];
    double buf[LADDER_BUF];
} PhiVec;

/* Paterson-Stockmeyer for phi1(Z) = sum_{i=0}^{16} Z^i / (i+1)! (||Z||_1 <= 1/2: the next term < 1e-19),
 * then E_0 = Z phi1(Z): 8 products instead of 17. */
static void expm1_small(int n, const double *Z, double *P, double *E)
{
    double Z2[NMAX * NMAX], Z3[NMAX * NMAX], Z4[NMAX * NMAX], T[NMAX * NMAX];
    double c[17];
    double f = 1.0;
    for (int i = 0; i < 17; i++) { f *= (double)(i + 1); c[i] = 1.0 / f; }
    int nn = n * n;
    matmul(n, Z, Z, Z2);
    matmul(n, Z2, Z, Z3);
    matmul(n, Z2, Z2, Z4);
    /* phi1 = C0 + Z4 (C1 + Z4 (C2 + Z4 (C3 + Z4 c16))), C_j = sum_{i<4} c_{4j+i} Z^i */
    for (int i = 0; i < nn; i++) P[i] = 0.0;
    for (int i = 0; i < n; i++) P[i * n + i] = c[16];
    for (int j = 3; j >= 0; j--) {
        matmul(n, Z4, P, T);
        for (int i = 0; i < nn; i++) P[i] = T[i] + c[4 * j + 1] * Z[i] + c[4 * j + 2] * Z2[i] + c[4 * j + 3] * Z3[i];
        for (int i = 0; i < n; i++) P[i * n + i] += c[4 * j];
    }
    matmul(n, Z, P, E);
}

/* The components of J (k x k) and the balancing of each, once per linearisation: both are the same for hJ
 * whatever h (balancing is invariant under scaling, and its powers of two commute with it exactly). */
static void phivec_prepare(PhiVec *P, int k, const double *J, double *guess)
{
    int label[NMAX];
    P->k = k;
    P->nc = components(k, J, label);
    for (int c = 0; c < P->nc; c++) {
        Ladder *L = &P->lad[c];
        int m = 0;
        for (int i = 0; i < k; i++)
            if (label[i] == c) L->idx[m++] = i;
        L->n = m;
        for (int a = 0; a < m; a++)
            for (int b = 0; b < m; b++) L->Jb[a * m + b] = J[L->idx[a] * k + L->idx[b]];
        if (!guess) { balance(m, L->Jb, L->d); continue; }
        for (int a = 0; a < m; a++) L->d[a] = guess[L->idx[a]];
        balance_from(m, L->Jb, L->d);
        for (int a = 0; a < m; a++) guess[L->idx[a]] = L->d[a];
    }
}

/* The ladder of one component for the step h into buf; 1 when it would need more than LADDER_LEVELS
 * squarings. */
static int ladder_build(Ladder *L, double h, double *buf)
{
    int n = L->n, nn = n * n;
    double norm = 0.0;
    for (int j = 0; j < n; j++) {
        double c = 0.0;
        for (int i = 0; i < n; i++) c += fabs(h * L->Jb[i * n + j]);
        if (c > norm) norm = c;
    }
    if (!isfinite(norm)) return 1;
    int s = norm > 0.5 ? (int)ceil(log2(norm / 0.5)) : 0;
    if (s > LADDER_LEVELS) return 1;
    L->s = s;
    double scale = ldexp(1.0, -s), *ZT = buf, *P1T = buf + nn, *E = buf + 2 * nn;
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) ZT[j * n + i] = (h * L->Jb[i * n + j]) * scale;
    expm1_small(n, ZT, P1T, E);
    for (int j = 0; j < s; j++) {
        double *Ej = E + (size_t)j * nn, *En = Ej + nn;
        matmul(n, Ej, Ej, En);
        for (int i = 0; i < nn; i++) En[i] += 2.0 * Ej[i];
    }
    L->ZT = ZT;
    L->P1T = P1T;
    L->ET = E;
    return 0;
}

/* p_k = phi_k(A) x for k = 0..kmax (p[k] may be NULL for k < kmax; p[kmax] must not be), x and p in the
 * block's own coordinates. */
static void ladder_apply(const Ladder *L, const double *x, int kmax, double *p[4])
{
    int n = L->n, nn = n * n;
    double xb[NMAX], q[4][NMAX], t[NMAX];
    for (int i = 0; i < n; i++) xb[i] = x[i] / L->d[i];
    if (kmax == 1) {
        matvec_t(n, L->P1T, xb, q[1]);   /* phi1(Z) xb from the matrix the ladder's bottom made */
    } else {
        /* bottom: phi_kmax(Z) xb by Horner over 17 - kmax terms, then phi_k = Z phi_{k+1} + xb / k! */
        double fact[21];
        fact[0] = 1.0;
        for (int i = 1; i < 21; i++) fact[i] = fact[i - 1] * i;
        int top = 17;                     /* the last term is Z^(17 - kmax) / 17!, as in expm1_small */
        for (int i = 0; i < n; i++) q[kmax][i] = xb[i] / fact[top];
        for (int e = top - 1; e >= kmax; e--) {
            matvec_t(n, L->ZT, q[kmax], t);
            for (int i = 0; i < n; i++) q[kmax][i] = t[i] + xb[i] / fact[e];
        }
        /* q[kmax] = sum_{i=0}^{top-kmax} Z^i xb / (i + kmax)! */
        for (int k = kmax - 1; k >= 1; k--) {
            matvec_t(n, L->ZT, q[k + 1], t);
            for (int i = 0; i < n; i++) q[k][i] = t[i] + xb[i] / fact[k];
        }
    }
    /* climb */
    for (int j = 0; j < L->s; j++) {
        const double *ET = L->ET + (size_t)j * nn;
        double e1[NMAX], e2[NMAX], e3[NMAX];
        if (kmax >= 1) matvec_t(n, ET, q[1], e1);
        if (kmax >= 2) matvec_t(n, ET, q[2], e2);
        if (kmax >= 3) matvec_t(n, ET, q[3], e3);
        for (int i = 0; i < n; i++) {
            double p1 = q[1][i], p2 = kmax >= 2 ? q[2][i] : 0.0;
            if (kmax >= 3) q[3][i] = 0.125 * (2.0 * q[3][i] + e3[i] + 0.5 * p1 + p2);
            if (kmax >= 2) q[2][i] = 0.25 * (2.0 * p2 + e2[i] + p1);
            q[1][i] = p1 + 0.5 * e1[i];
        }
    }
    if (p[0]) {
        matvec_t(n, L->ET + (size_t)L->s * nn, xb, t);
        for (int i = 0; i < n; i++) p[0][i] = (xb[i] + t[i]) * L->d[i];
    }
    for (int k = 1; k <= kmax; k++)
        if (p[k])
            for (int i = 0; i < n; i++) p[k][i] = q[k][i] * L->d[i];
}

/* The ladders of every component of P (prepared) for the step h; 1 when one would be too deep. */
static int phivec_build(PhiVec *P, double h)
{
    size_t used = 0;
    for (int c = 0; c < P->nc; c++) {
        Ladder *L = &P->lad[c];
        size_t mm = (size_t)L->n * L->n;
        if (used + (size_t)(LADDER_LEVELS + 3) * mm > LADDER_BUF) return 1;
        if (ladder_build(L, h, P->buf + used)) return 1;
        used += (size_t)(L->s + 3) * mm;
    }
    return 0;
}

size_t solver_work_size(void)
{
    return sizeof(PhiVec);
}

/* p_k = phi_k(A) x, k = 0..kmax, for the whole block (p[k] NULL: not wanted, except p[kmax]). */
static void phivec_apply(const PhiVec *P, const double *x, int kmax, double *p[4])
{
    for (int c = 0; c < P->nc; c++) {
        const Ladder *L = &P->lad[c];
        int m = L->n;
        double xc[NMAX], pc[4][NMAX], *pp[4];
        for (int a = 0; a < m; a++) xc[a] = x[L->idx[a]];
        for (int k = 0; k < 4; k++) pp[k] = (k <= kmax && p[k]) ? pc[k] : NULL;
        ladder_apply(L, xc, kmax, pp);
        for (int k = 0; k <= kmax; k++)
            if (p[k])
                for (int a = 0; a < m; a++) p[k][L->idx[a]] = pc[k][a];
    }
}

void solver_phi_apply(int n, const double *A, const double *x, double *P0, double *P1, double *P2, double *P3)
{
    PhiVec *P = malloc(sizeof(PhiVec));
    if (!P) return;
    double *p[4] = {P0, P1, P2, P3};
    phivec_prepare(P, n, A, NULL);
    if (phivec_build(P, 1.0) == 0) phivec_apply(P, x, 3, p);
    else for (int i = 0; i < n; i++) P0[i] = P1[i] = P2[i] = P3[i] = NAN;
    free(P);
}

/* ---------------------------------------------------------------- linearisation */

typedef struct {
    int k;                       /* active states */
    int idx[NMAX];
    int active[NMAX];
    double F0[NMAX], Ft[NMAX];
    double J[NMAX * NMAX];       /* n x n; only the active states' columns are filled */
    double Jfull[NMAX * NMAX];   /* the model's whole Jacobian at (t, u) */
    double t;
    double u[NMAX];
} Linearization;

static int eval_real(Solver *s, double t, const double *u, double *F, char *msg, size_t len)
{
    s->n_rhs++;
    if (s->rhs(s->ctx, t, u, F, msg, len)) return 1;
    for (int i = 0; i < s->n; i++) {
        if (!isfinite(F[i])) {
            snprintf(msg, len, "the right-hand side is not finite at t = %.17g (state %d)", t, i);
            return 1;
        }
    }
    return 0;
}

/* Add to the active set every state driven by an active one, and fill the new columns. */
static void close_active_set(Solver *s, Linearization *L, int *filled)
{
    int n = s->n, changed = 1;
    while (changed) {
        changed = 0;
        for (int j = 0; j < n; j++) {
            if (!L->active[j] || filled[j]) continue;
            for (int i = 0; i < n; i++) L->J[i * n + j] = L->Jfull[i * n + j];
            filled[j] = 1;
            for (int i = 0; i < n; i++)
                if (!L->active[i] && L->J[i * n + j] != 0.0) { L->active[i] = 1; changed = 1; }
        }
    }
    L->k = 0;
    for (int i = 0; i < n; i++)
        if (L->active[i]) L->idx[L->k++] = i;
}

static int linearize(Solver *s, double t, const double *u, Linearization *L, char *msg, size_t len)
{
    int n = s->n;
    L->t = t;
    memcpy(L->u, u, sizeof(double) * n);
    s->n_rhs++;
    if (s->lin(s->ctx, t, u, L->F0, L->Jfull, L->Ft, msg, len)) return 1;
    for (int i = 0; i < n; i++) {
        if (!isfinite(L->F0[i]) || !isfinite(L->Ft[i])) {
            snprintf(msg, len, "the right-hand side is not finite at t = %.17g (state %d)", t, i);
            return 1;
        }
        L->active[i] = (u[i] != 0.0 || L->F0[i] != 0.0 || L->Ft[i] != 0.0);
    }
    memset(L->J, 0, sizeof(double) * n * n);
    int filled[NMAX] = {0};
    close_active_set(s, L, filled);
    for (int a = 0; a < L->k; a++)
        for (int i = 0; i < n; i++)
            if (!isfinite(L->J[i * n + L->idx[a]])) {
                snprintf(msg, len, "the Jacobian is not finite at t = %.17g (state %d)", t, L->idx[a]);
                return 1;
            }
    /* In the linear regime (same Jacobian as the last step) keep the carried derivative wherever it agrees
     * with the evaluated one within the evaluation's rounding error: there it is the more accurate. */
    if (s->z_valid && memcmp(L->J, s->J_prev, sizeof(double) * n * n) == 0) {
        for (int i = 0; i < n; i++) {
            if (!L->active[i]) continue;
            double mag = fabs(L->F0[i]);
            for (int j = 0; j < n; j++) mag += fabs(L->J[i * n + j] * u[j]);
            if (fabs(L->F0[i] - s->z[i]) <= 8.0 * DBL_EPSILON * mag) L->F0[i] = s->z[i];
        }
    }
    memcpy(s->J_prev, L->J, sizeof(double) * n * n);
    return 0;
}

/* ---------------------------------------------------------------- monitors */

/* Max of |p| on a cubic Hermite piece (p0, d0) -> (p1, d1) of length dt. */
static double hermite_absmax(double p0, double d0, double p1, double d1, double dt)
{
    double m = fmax(fabs(p0), fabs(p1));
    /* p(x) = p0 + d0 dt x + a x^2 + b x^3, x in [0, 1] */
    double a = 3.0 * (p1 - p0) - (2.0 * d0 + d1) * dt;
    double b = 2.0 * (p0 - p1) + (d0 + d1) * dt;
    double c1 = d0 * dt;                 /* p'(x) = c1 + 2a x + 3b x^2 */
    double roots[2];
    int nr = 0;
    if (fabs(b) > 1e-300) {
        double disc = 4.0 * a * a - 12.0 * b * c1;
        if (disc >= 0.0) {
            double sq = sqrt(disc);
            double q = -0.5 * (2.0 * a + (a >= 0 ? sq : -sq));
            if (q != 0.0) roots[nr++] = q / (3.0 * b);
            if (q != 0.0) roots[nr++] = c1 / q;
        }
    } else if (a != 0.0) {
        roots[nr++] = -c1 / (2.0 * a);
    }
    for (int r = 0; r < nr; r++) {
        double x = roots[r];
        if (x > 0.0 && x < 1.0) m = fmax(m, fabs(p0 + x * (c1 + x * (a + x * b))));
    }
    return m;
}

/* ---------------------------------------------------------------- the step */

typedef struct {
    double h;
    double phs[4][NMAX * NMAX];    /* phi_k(h J / 8), active block */
    double phf[4][NMAX * NMAX];    /* phi_k(h J) */
} Phis;

static void active_block(const Solver *s, const Linearization *L, double h, double *A)
{
    int k = L->k, n = s->n;
    for (int a = 0; a < k; a++)
        for (int b = 0; b < k; b++) A[a * k + b] = h * L->J[L->idx[a] * n + L->idx[b]];
}

/* Exact solution of the linearised dynamics dw/ds = z, dz/ds = J z + Ft over a sub-step dt from (w0, z0),
 * with the phi functions of dt J: w1 = w0 + dt phi1 z0 + dt^2 phi2 Ft, z1 = phi0 z0 + dt phi1 Ft. Carrying z
 * instead of re-evaluating F0 + J (w - u) avoids cancellation in the acceleration. */
static void propagate_linear(const Solver *s, const Linearization *L, const double *w0, const double *z0,
                             double dt, double ph[4][NMAX * NMAX], double *w1, double *z1)
{
    int n = s->n, k = L->k;
    double za[NMAX], Fta[NMAX], y1[NMAX], y2[NMAX], y0[NMAX], yt[NMAX];
    for (int a = 0; a < k; a++) { za[a] = z0[L->idx[a]]; Fta[a] = L->Ft[L->idx[a]]; }
    matvec(k, ph[1], za, y1);
    matvec(k, ph[2], Fta, y2);
    matvec(k, ph[0], za, y0);
    matvec(k, ph[1], Fta, yt);
    memcpy(w1, w0, sizeof(double) * n);
    if (z1) memcpy(z1, z0, sizeof(double) * n);
    for (int a = 0; a < k; a++) {
        int i = L->idx[a];
        w1[i] += dt * y1[a] + dt * dt * y2[a];
        if (z1) z1[i] = y0[a] + dt * yt[a];
    }
}

static int at_rest(const Solver *s, double v, double a)
{
    return fabs(v) <= s->eps_v && fabs(a) <= s->eps_a;
}

/* g(t) = max(|v|/eps_v, |a|/eps_a) - 1 on the exact linearised solution from a sample (w0, z0). */
static double rest_gap(const Solver *s, const Linearization *L, const double *w0, const double *z0, double dt)
{
    double w1[NMAX], z1[NMAX], A[NMAX * NMAX];
    double ph[4][NMAX * NMAX];
    active_block(s, L, dt, A);
    solver_phi(L->k, A, ph[0], ph[1], ph[2], ph[3]);
    propagate_linear(s, L, w0, z0, dt, ph, w1, z1);
    return fmax(fabs(w1[s->ivel]) / s->eps_v, fabs(z1[s->ivel]) / s->eps_a) - 1.0;
}

/* Time in (0, dt] after sample (s0, w0) where the rest condition starts to hold (g goes from > 0 to
 * <= 0), by the Illinois variant of regula falsi on the exact linearised solution. */
static double locate_rest(const Solver *s, const Linearization *L, const double *w0, const double *z0,
                          double dt, double g0, double g1)
{
    double lo = 0.0, hi = dt, glo = g0, ghi = g1;
    int side = 0;
    double tol = 1e-13 * fmax(1.0, fabs(L->t)) + 1e-16;
    for (int it = 0; it < 200 && hi - lo > tol; it++) {
        double x = (glo * hi - ghi * lo) / (glo - ghi);
        if (!(x > lo && x < hi)) x = 0.5 * (lo + hi);
        double gx = rest_gap(s, L, w0, z0, x);
        if (fabs(gx) < 1e-12) return x;     /* g is |v|/eps_v or |a|/eps_a minus 1: converged */
        if (gx > 0.0) {
            lo = x; glo = gx;
            if (side == -1) ghi *= 0.5;
            side = -1;
        } else {
            hi = x; ghi = gx;
            if (side == 1) glo *= 0.5;
            side = 1;
        }
    }
    return hi;
}

/* A lightly damped axial oscillation can have peaks of |a_y| or |v_y| above the rest thresholds between
 * samples while every sample is below them, so t_eq would come out too early. When the active block is
 * the 2x2 axial one with complex eigenvalues sigma +- i omega, the solution of the linearised dynamics is a
 * particular part (affine in time) plus a damped oscillation whose amplitude is known in closed form;
 * from the start s_c of the rest found by the samples to the time s* after which the envelope stays
 * below the thresholds, the exact solution is scanned at 1/16 of the period for the last excursion, and
 * t_eq moves to where that excursion ends. Returns the corrected start of rest in step coordinates. */
static double rest_after_oscillation(const Solver *s, const Linearization *L, const double *w0,
                                     const double *z0, double h, double s_c)
{
    if (L->k != 2) return s_c;
    int ip = s->ipos, iv = s->ivel, n = s->n;
    if (!((L->idx[0] == ip && L->idx[1] == iv) || (L->idx[0] == iv && L->idx[1] == ip))) return s_c;
    double Jpp = L->J[ip * n + ip], Jpv = L->J[ip * n + iv], Jvp = L->J[iv * n + ip], Jvv = L->J[iv * n + iv];
    double tr = Jpp + Jvv, det = Jpp * Jvv - Jpv * Jvp, disc = tr * tr - 4.0 * det;
    if (!(disc < 0.0) || det == 0.0) return s_c;
    double sigma = 0.5 * tr, omega = 0.5 * sqrt(-disc);
    if (!(sigma < 0.0)) return s_c;
    /* x = w - w0 obeys x' = J x + z0 + Ft s (z0 = the derivative at the sample, Ft the forcing slope) */
    double Fp = L->Ft[ip], Fv = L->Ft[iv], Zp = z0[ip], Zv = z0[iv];
    double ip_ = 1.0 / det;   /* J^-1 = [[Jvv, -Jpv], [-Jvp, Jpp]] / det */
    double q1p = -ip_ * (Jvv * Fp - Jpv * Fv), q1v = -ip_ * (-Jvp * Fp + Jpp * Fv);
    double rp = q1p - Zp, rv = q1v - Zv;
    double q0p = ip_ * (Jvv * rp - Jpv * rv), q0v = ip_ * (-Jvp * rp + Jpp * rv);
    double hp = -q0p, hv = -q0v;                       /* the oscillation at the sample */
    double ghp = Jpp * hp + Jpv * hv, ghv = Jvp * hp + Jvv * hv;   /* its derivative */
    /* amplitude of component c of e^{Js} x: sqrt(x_c^2 + (((J - sigma) x)_c / omega)^2) */
    double Av = hypot(hv, (Jvp * hp + (Jvv - sigma) * hv) / omega);
    double Aa = hypot(ghv, (Jvp * ghp + (Jvv - sigma) * ghv) / omega);
    double ap = fabs(q1v);
    double vp = fmax(fabs(w0[iv] + q0v + q1v * s_c), fabs(w0[iv] + q0v + q1v * h));
    if (ap >= s->eps_a || vp >= s->eps_v) return s_c;   /* the samples' verdict stands */
    double s_a = Aa > s->eps_a - ap ? log((s->eps_a - ap) / Aa) / sigma : 0.0;
    double s_v = Av > s->eps_v - vp ? log((s->eps_v - vp) / Av) / sigma : 0.0;
    double s_star = fmin(fmax(s_a, s_v), h);
    if (s_star <= s_c) return s_c;
    double dt = 3.14159265358979323846 / omega / 8.0;   /* 1/16 of the period */
    for (double x = s_star; x > s_c; x -= dt) {
        double xs = fmax(x, s_c);
        if (rest_gap(s, L, w0, z0, xs) > 0.0) {
            /* the last excursion: rest begins at the next upward-to-rest crossing after xs */
            double x1 = fmin(xs + dt, h), g0 = rest_gap(s, L, w0, z0, xs), g1 = rest_gap(s, L, w0, z0, x1);
            if (g1 > 0.0) return x1;   /* unresolved: take the conservative end */
            double w1[NMAX], z1[NMAX], A[NMAX * NMAX];
            double ph[4][NMAX * NMAX];
            active_block(s, L, xs, A);
            solver_phi(L->k, A, ph[0], ph[1], ph[2], ph[3]);
            propagate_linear(s, L, w0, z0, xs, ph, w1, z1);
            return xs + locate_rest(s, L, w1, z1, x1 - xs, g0, g1);
        }
    }
    return s_c;
}

/* ---------------------------------------------------------------- exact pieces of a linear 2-state block
 *
 * When the model declares the (position, velocity) block exactly linear (s->lin2) and the active set is
 * that block alone, the dynamics between two kinks of the load are y' = v, v' = -k y - g v + f(t)/m with
 * f affine: the exact solution is affine plus a homogeneous solution of the damped oscillator, written
 * with E(s) = e^{sigma s} cosh(mu s) and S(s) = e^{sigma s} sinh(mu s)/mu (cos and sin / omega when the
 * eigenvalues are complex), e^{sJ} = E I + S (J - sigma I). One step covers the whole piece; the monitors
 * come from the closed form: extrema at the roots of the derivative (closed-form zeros of a homogeneous
 * solution, or bracketed on its monotone intervals and solved by safeguarded Newton), the integrals in
 * closed form, and the start of the rest by the geometric decay of the oscillation's extrema. When a piece
 * would need too many roots (a long, undamped oscillation under a ramp) the general stepper takes it. */

typedef struct {
    double k, g, sigma, mu, lam1, lam2;
    int under;                    /* complex eigenvalues sigma +- i mu */
} Osc;

#define PIECE_MAX_ROOTS 4096
#define PIECE_PI 3.14159265358979323846

static void osc_init(Osc *o, double k, double g)
{
    o->k = k;
    o->g = g;
    o->sigma = -0.5 * g;
    double disc = 0.25 * g * g - k;
    if (disc < 0.0) {
        o->under = 1;
        o->mu = sqrt(-disc);
        o->lam1 = o->lam2 = 0.0;
    } else {
        o->under = 0;
        o->mu = sqrt(disc);
        o->lam2 = o->sigma - o->mu;     /* the fast one, no cancellation */
        o->lam1 = k / o->lam2;          /* the slow one from the product of the eigenvalues */
    }
}

/* Em = E - sigma S, Ep = E + sigma S and S at s: phi_x(s) = x1 Em + x2 S, phi_x'(s) = x2 Ep - k x1 S. */
static void osc_es(const Osc *o, double s, double *Em, double *Ep, double *S)
{
    if (o->under) {
        double e = exp(o->sigma * s), c = cos(o->mu * s), sn = sin(o->mu * s) / o->mu;
        *S = e * sn;
        *Em = e * (c - o->sigma * sn);
        *Ep = e * (c + o->sigma * sn);
    } else if (o->mu * s < 0.5) {
        double x = o->mu * s, e = exp(o->sigma * s), ch = cosh(x), sc = x == 0.0 ? s : sinh(x) / o->mu;
        *S = e * sc;
        *Em = e * (ch - o->sigma * sc);
        *Ep = e * (ch + o->sigma * sc);
    } else {
        double e1 = exp(o->lam1 * s), e2 = exp(o->lam2 * s), dl = o->lam1 - o->lam2;
        *S = (e1 - e2) / dl;
        *Em = (o->lam1 * e2 - o->lam2 * e1) / dl;
        *Ep = (o->lam1 * e1 - o->lam2 * e2) / dl;
    }
}

/* The piece in the phi-function form: w(s) = w0 + s phi1(sJ) z0 + s^2 phi2(sJ) Ft, z(s) = phi0(sJ) z0 +
 * s phi1(sJ) Ft (z = (v, a), Ft = (0, f)), evaluated with solver_phi: free of the cancellation between
 * the particular and the homogeneous parts that the modal form suffers when the piece is short against
 * the slow mode. Used for the end state and wherever the modal form cancels. */
typedef struct {
    double k, g, y0, v0, a0, f;
} Piece;

static void piece_exact(const Piece *P, double s, double *y, double *v, double *a, double *yint)
{
    double A[4] = {0.0, s, -P->k * s, -P->g * s}, p0[4], p1[4], p2[4], p3[4];
    solver_phi(2, A, p0, p1, p2, p3);
    if (y) *y = P->y0 + s * (p1[0] * P->v0 + p1[1] * P->a0) + s * s * p2[1] * P->f;
    if (v) *v = p0[0] * P->v0 + p0[1] * P->a0 + s * p1[1] * P->f;
    if (a) *a = p0[2] * P->v0 + p0[3] * P->a0 + s * p1[3] * P->f;
    if (yint) *yint = P->y0 * s + s * s * (p2[0] * P->v0 + p2[1] * P->a0) + s * s * s * p3[1] * P->f;
}

/* f(s) = a + b s + phi_x(s) and f'(s); which: 0 = y, 1 = v, 2 = a of the piece (exact fallback), -1 none */
typedef struct { double a, b, x1, x2; int which; const Piece *P; } Fn;

static void fn_eval(const Osc *o, const Fn *f, double s, double *val, double *der)
{
    double Em, Ep, S;
    osc_es(o, s, &Em, &Ep, &S);
    double t1 = f->b * s, t2 = f->x1 * Em, t3 = f->x2 * S;
    *val = f->a + t1 + t2 + t3;
    if (der) *der = f->b + f->x2 * Ep - o->k * f->x1 * S;
    if (f->which >= 0 && !(fabs(*val) >= 1e-5 * (fabs(f->a) + fabs(t1) + fabs(t2) + fabs(t3)))) {
        double y, v, a;
        piece_exact(f->P, s, &y, &v, &a, NULL);
        *val = f->which == 0 ? y : f->which == 1 ? v : a;
        if (der && f->which == 0) *der = v;
        else if (der && f->which == 1) *der = a;
    }
}

static double fn_val(const Osc *o, const Fn *f, double s)
{
    double v;
    fn_eval(o, f, s, &v, NULL);
    return v;
}

/* the derivative as a function of the same form */
static Fn fn_der(const Osc *o, const Fn *f)
{
    Fn d = {f->b, 0.0, f->x2, -o->k * f->x1 - o->g * f->x2, f->which >= 0 && f->which < 2 ? f->which + 1 : -1,
            f->P};
    return d;
}

/* Zeros in (0, h) of the homogeneous phi_x: underdamped, s_j = s0 + j p (returns 1 and s0, p; *n the
 * count in (0, h)); real eigenvalues, at most one (p = 0). */
static void hom_zeros(const Osc *o, double x1, double x2, double h, double *s0, double *p, long *n)
{
    *n = 0;
    *p = 0.0;
    *s0 = 0.0;
    if (x1 == 0.0 && x2 == 0.0) return;
    if (o->under) {
        double th = atan2((x2 - o->sigma * x1) / o->mu, x1);
        double base = th + 0.5 * PIECE_PI;
        while (base <= 0.0) base += PIECE_PI;
        while (base > PIECE_PI) base -= PIECE_PI;
        *s0 = base / o->mu;
        *p = PIECE_PI / o->mu;
        if (*s0 < h) {   /* capped: a long is 32 bits on Windows, and callers compare with far smaller caps */
            double c = floor((h - *s0) / *p) + 1.0;
            *n = c > 1e9 ? 1000000000L : (long)c;
        }
        while (*n > 0 && *s0 + (*n - 1) * *p >= h) (*n)--;
        return;
    }
    double den = x2 - o->sigma * x1;
    if (den == 0.0) return;
    double r = -x1 / den, s;
    if (!(r > 0.0)) return;
    if (o->mu == 0.0) s = r;
    else {
        double mr = o->mu * r;
        if (!(mr < 1.0)) return;
        s = atanh(mr) / o->mu;
    }
    if (s > 0.0 && s < h) { *s0 = s; *n = 1; }
}

/* Root of f(s) = target on [l, r] where f is monotone and f(l) - target, f(r) - target differ in sign:
 * Newton safeguarded by bisection. */
static double fn_solve(const Osc *o, const Fn *f, double target, double l, double r)
{
    double fl = fn_val(o, f, l) - target;
    double x = 0.5 * (l + r);
    for (int it = 0; it < 100; it++) {
        double fx, dx;
        fn_eval(o, f, x, &fx, &dx);
        fx -= target;
        if (fx == 0.0) return x;
        if ((fx > 0.0) == (fl > 0.0)) { l = x; fl = fx; } else r = x;
        double xn = dx != 0.0 ? x - fx / dx : 0.5 * (l + r);
        if (!(xn > l && xn < r)) xn = 0.5 * (l + r);
        if (r - l <= 4.0 * DBL_EPSILON * fmax(fabs(l), fabs(r)) || fabs(xn - x) <= 2.0 * DBL_EPSILON * fabs(x)) {
            x = xn;
            break;
        }
        x = xn;
    }
    return x;
}

/* Roots in (0, h) of v = B + phi_h0 (no slope): closed form when B = 0; otherwise one per monotone interval
 * of v with a sign change, the intervals bounded by the closed-form zeros of a = phi_dh0, stopping where
 * the oscillation's envelope falls below |B|. Returns the count, -1 beyond cap. */
static long v_roots(const Osc *o, const Fn *v, double h, double *roots, long cap)
{
    long n = 0;
    if (v->b != 0.0) return -1;
    if (v->a == 0.0) {                      /* v homogeneous: its zeros in closed form */
        double s0, p;
        long m;
        hom_zeros(o, v->x1, v->x2, h, &s0, &p, &m);
        if (m > cap) return -1;
        for (long j = 0; j < m; j++) roots[n++] = s0 + j * p;
        return n;
    }
    Fn a = fn_der(o, v);                    /* homogeneous (a.a = a.b = 0) */
    double s0, p;
    long m;
    hom_zeros(o, a.x1, a.x2, h, &s0, &p, &m);
    double amp = o->under ? hypot(v->x1, (v->x2 - o->sigma * v->x1) / o->mu) : INFINITY;
    if (o->under && m > 2 * cap) {   /* more intervals above |B| than roots allowed: say so before solving any */
        double B = fabs(v->a);
        double s_stop = amp <= B ? 0.0 : o->sigma < 0.0 ? log(B / amp) / o->sigma : h;
        if (fmin(s_stop, h) > s0 + 2.0 * cap * p) return -1;
    }
    double l = 0.0, vl = fn_val(o, v, 0.0);
    for (long j = 0; j <= m; j++) {
        if (o->under && amp * exp(o->sigma * l) < fabs(v->a)) break;   /* v keeps the sign of B */
        if (j > cap * 4) return -1;
        double r = j < m ? s0 + j * p : h, vr = fn_val(o, v, r);
        if ((vl < 0.0 && vr > 0.0) || (vl > 0.0 && vr < 0.0)) {
            if (n >= cap) return -1;
            roots[n++] = fn_solve(o, v, 0.0, l, r);
        }
        l = r;
        vl = vr;
    }
    return n;
}

/* max |f| on [0, h] for f = a + phi_x (no slope): endpoints and the critical points; the values at the
 * critical points s0 + j p alternate in sign and decay geometrically, so only the first two and the last
 * two can be the largest. */
static double maxabs_flat(const Osc *o, const Fn *f, double h)
{
    double m = fmax(fabs(fn_val(o, f, 0.0)), fabs(fn_val(o, f, h)));
    Fn d = fn_der(o, f);
    double s0, p;
    long n;
    hom_zeros(o, d.x1, d.x2, h, &s0, &p, &n);
    long js[4] = {0, 1, n - 2, n - 1};
    for (int i = 0; i < 4; i++)
        if (js[i] >= 0 && js[i] < n) m = fmax(m, fabs(fn_val(o, f, s0 + js[i] * p)));
    return m;
}

/* The last s in [0, h] with |f(s)| >= eps for f = a + phi_x, given |f(h)| <= eps; -1 if none, -2 when it
 * would take too long. */
static double last_exceed(const Osc *o, const Fn *f, double eps, double h)
{
    Fn d = fn_der(o, f);
    double s0, p;
    long n;
    hom_zeros(o, d.x1, d.x2, h, &s0, &p, &n);
    long jhi = n - 1;
    if (n > 0 && o->under && o->sigma < 0.0 && fabs(f->a) < eps) {
        double c0 = fabs(fn_val(o, f, s0) - f->a), thr = eps - fabs(f->a);
        if (c0 > thr) {
            double j = ceil(log(thr / c0) / (o->sigma * p));
            if (j < (double)jhi) jhi = (long)j;
        } else jhi = -1;
    }
    long count = 0;
    for (long j = jhi; j >= -1; j--) {
        double l = j >= 0 ? s0 + j * p : 0.0;
        double fl = fn_val(o, f, l);
        if (fabs(fl) >= eps) {
            double r = j + 1 < n ? s0 + (j + 1) * p : h;
            if (fabs(fl) == eps) return l;
            return fn_solve(o, f, copysign(eps, fl), l, r);
        }
        if (++count > 4 * PIECE_MAX_ROOTS) return -2.0;
    }
    return -1.0;
}

/* The monitors of a piece (piece_monitors) on top of the solver's so far. */
typedef struct { double pos_max, vel_max, pint, vint, t_eq; } PieceMonitors;

/* A piece under constant forcing whose damped oscillation rings for more than PIECE_MAX_ROOTS half-periods (a
 * stiff element held after a ramp: c = 1e16 N/m rings at 1 GHz for microseconds, a piece lasts seconds): v is
 * homogeneous, its zeros are s0 + j p, and y at them departs from its centre y_c by d0 (-r)^j, r = e^(sigma p),
 * exactly. The extrema are the first two, and the integral of |v|, the sum of |dy| between them, is a
 * geometric series. Adds both to m; 0 when the piece is not of that kind. */
static int ringing_extrema(const Osc *o, const Fn *Y, const Fn *V, double h, double y0, double yH,
                           PieceMonitors *m)
{
    if (V->a != 0.0 || V->b != 0.0 || Y->b != 0.0 || !o->under || !(o->sigma < 0.0)) return 0;
    double s0, p;
    long count;
    hom_zeros(o, V->x1, V->x2, h, &s0, &p, &count);
    if (count < 2) return 0;
    double md = floor((h - s0) / p) + 1.0;        /* the count, beyond what a long holds */
    while (md > 1.0 && s0 + (md - 1.0) * p >= h) md -= 1.0;
    double yc = Y->a, y1 = fn_val(o, Y, s0), d0 = y1 - yc, sp = o->sigma * p, r = exp(sp);
    double decay = exp(sp * (md - 1.0));                                   /* r^(md - 1) */
    double sum = fabs(d0) * (1.0 + r) * (-expm1(sp * (md - 1.0))) / (-expm1(sp));
    double y_last = yc + d0 * decay * (fmod(md - 1.0, 2.0) == 0.0 ? 1.0 : -1.0);
    m->pos_max = fmax(m->pos_max, fmax(fabs(y1), fabs(yc - r * d0)));
    m->vint += fabs(y1 - y0) + sum + fabs(yH - y_last);
    return 1;
}

/* The monitors of the (position, velocity) block over a piece of length h from the closed form of P, on top of
 * the solver's monitors so far: the extrema of y at the roots of v, max |v| at the zeros of a, the integrals
 * of y (yint) and |v|, and the start of the rest. (yH, vH, aH) is the piece's end. Returns 0, or -1 when the
 * piece would need more than PIECE_MAX_ROOTS roots (nothing is written then). */
static int piece_monitors(const Solver *s, const Piece *P, double h, double yH, double vH, double aH, double yint,
                          PieceMonitors *out)
{
    double k = P->k, g = P->g, y0 = P->y0, v0 = P->v0, a0 = P->a0;
    Osc o;
    osc_init(&o, k, g);
    double B = P->f / k;
    double h1 = v0 - B, h2 = a0;                 /* h0 = z0 - z_p */
    double q1 = -(g * h1 + h2) / k, q2 = h1;     /* q = J^-1 h0 */
    Fn Y = {y0 - q1, B, q1, q2, 0, P}, Vf = {B, 0.0, h1, h2, 1, P}, Af = fn_der(&o, &Vf);
    double roots[PIECE_MAX_ROOTS];
    long nr = v_roots(&o, &Vf, h, roots, PIECE_MAX_ROOTS);
    PieceMonitors m = {s->pos_max, s->vel_max, 0.0, 0.0, s->t_eq};
    m.pos_max = fmax(m.pos_max, fmax(fabs(y0), fabs(yH)));
    if (nr < 0 && !ringing_extrema(&o, &Y, &Vf, h, y0, yH, &m)) return -1;
    /* y at the roots of v: its extrema; the integral of |v| is the sum of |dy| between them */
    double yl = y0;
    for (long j = 0; j <= nr; j++) {
        double sr = j < nr ? roots[j] : h, yr = j < nr ? fn_val(&o, &Y, sr) : yH;
        m.pos_max = fmax(m.pos_max, fabs(yr));
        m.vint += fabs(yr - yl);
        yl = yr;
    }
    m.vel_max = fmax(m.vel_max, maxabs_flat(&o, &Vf, h));
    m.pint = yint;
    /* rest: the last time in the piece at which |v| >= eps_v or |a| >= eps_a */
    if (!at_rest(s, vH, aH)) m.t_eq = -1.0;
    else {
        double lv = last_exceed(&o, &Vf, s->eps_v, h), la = last_exceed(&o, &Af, s->eps_a, h);
        if (lv < -1.5 || la < -1.5) return -1;
        double last = fmax(lv, la);
        if (last >= 0.0) m.t_eq = s->t + last;
        else if (m.t_eq < 0.0) m.t_eq = s->t;
    }
    *out = m;
    return 0;
}

static void take_piece_monitors(Solver *s, const PieceMonitors *m)
{
    s->pos_max = m->pos_max;
    s->vel_max = m->vel_max;
    s->pos_int += m->pint;
    s->absvel_int += m->vint;
    s->t_eq = m->t_eq;
}

/* One exact step over the whole piece [t, t + h]. Returns 0 when taken, -1 when the general stepper must
 * take it (nothing changed), 1 on an error of the model. */
static int linear_piece(Solver *s, const Linearization *L, double h, double t_next, char *msg, size_t len)
{
    int n = s->n, ip = s->ipos, iv = s->ivel;
    if (!s->lin2 || s->h_max > 0.0 || L->k != 2 || s->ns) return -1;
    if (!((L->idx[0] == ip && L->idx[1] == iv) || (L->idx[0] == iv && L->idx[1] == ip))) return -1;
    if (L->J[ip * n + ip] != 0.0 || L->J[ip * n + iv] != 1.0 || L->Ft[ip] != 0.0) return -1;
    double k = -L->J[iv * n + ip], g = -L->J[iv * n + iv];
    if (!(k > 0.0) || !(g >= 0.0) || !isfinite(k) || !isfinite(g)) return -1;
    Piece P = {k, g, s->u[ip], s->u[iv], L->F0[iv], L->Ft[iv]};
    double yH, vH, aH, yint;
    piece_exact(&P, h, &yH, &vH, &aH, &yint);
    double u1[NMAX];
    memcpy(u1, s->u, sizeof(double) * n);
    u1[ip] = yH;
    u1[iv] = vH;
    PieceMonitors mon = {s->pos_max, s->vel_max, 0.0, 0.0, s->t_eq};
    if (s->monitors && piece_monitors(s, &P, h, yH, vH, aH, yint, &mon)) return -1;
    /* the inactive states must stay at rest: check the derivative at the end */
    double F1[NMAX];
    if (eval_real(s, t_next, u1, F1, msg, len)) return 1;
    for (int i = 0; i < n; i++)
        if (i != ip && i != iv && (F1[i] != 0.0 || u1[i] != 0.0)) return -1;
    take_piece_monitors(s, &mon);
    for (int i = 0; i < n; i++) s->umax[i] = fmax(s->umax[i], fabs(u1[i]));
    memcpy(s->u, u1, sizeof(double) * n);
    s->t = t_next;
    s->acc = aH;
    memcpy(s->z, F1, sizeof(double) * n);
    s->z[ip] = vH;
    s->z[iv] = aH;
    s->z_valid = 1;
    s->n_steps++;
    return 0;
}

/* ---------------------------------------------------------------- forward sensitivities
 *
 * Each column S = du/dp (one parameter) obeys the linear equation S' = J(t, u(t)) S + f_p(t, u(t)) along the
 * states' solution. Over every accepted step of the states from (t, u0) to (t + h, u1) the columns take steps of
 * the same exponential Rosenbrock scheme (exprb32) with the states' exact Jacobian J at the step's start:
 *     S_U = S + k phi1(kJ) G0 + k^2 phi2(kJ) G_t,  S1 = S_U + 2k phi3(kJ) D,
 *     D = G(t + k, u(t + k), S_U) - G0 - J (S_U - S) - k G_t,
 * with G = J S + f_p and G_t its derivative in time at fixed S along the states' motion (u' = f; the model's own where
 * it gives it, else a forward difference: sens_rates), so that the change of J and f_p enters as the time dependence
 * of a linear equation. At a step's start where the columns' last sub-step ended, G0 and G_t come from that sub-step
 * instead (sens_from_history: G is affine in S with the exact J, G_t the secant along it), so a sub-step calls the
 * model's sensitivity equations once, at its end. The columns take their sub-steps together
 * (one evaluation of the model's sensitivity equations for all, one set of phi functions). A sub-step k of the
 * state's step is accepted when every column's correction 2k phi3 D is within sens_rtol (0: rtol) of the column's
 * scale (each state's largest |S| so far, or its largest |u| divided by |p|, what a change of p by itself moves it).
 * A column that misses it takes the sub-step again together with the states (sens_substep_aug: the states' motion
 * enters S through the Jacobian of G by the states, not as a polynomial in time, which a screw ringing at kHz through
 * a step of 30 ms needs a hundred sub-steps to follow); if that misses too, the sub-step is shortened. The states
 * inside the step come from its linearised solution (exact where the step was linear), its end is the accepted u1.
 * The block is that of the states that move or whose sensitivity does (closed under J's coupling). The states' steps
 * are their own, so
 * a run with sensitivities has the same states as one without. Where the right-hand side switches (a kink of the
 * load, the Bouc-Wen switch of friction and yield, a rounded corner sharper than a step) S follows the side of the
 * step's start: the derivative is the one-sided one. */

/* The states at t + tau inside the step from (t, u0) on its linearised solution. */
static void sens_state_at(const Solver *s, const Linearization *L, const double *u0, double tau, double *u)
{
    double A[NMAX * NMAX], ph[4][NMAX * NMAX];
    if (L->k == 0) { memcpy(u, u0, sizeof(double) * s->n); return; }
    active_block(s, L, tau, A);
    solver_phi(L->k, A, ph[0], ph[1], ph[2], ph[3]);
    propagate_linear(s, L, u0, L->F0, tau, ph, u, NULL);
}

/* The phi functions of the last sub-step's k J on its block, for the next column that takes the same sub-step
 * (within one step of the states J is the same for every column, and most columns take the whole step). */
typedef struct {
    int valid, m, idx[NMAX];
    double k, P1[NMAX * NMAX], P2[NMAX * NMAX], P3[NMAX * NMAX];
} SensPhis;

/* phi_1..3 of k J on the block idx (m states), kept while k and the block stay the same. */
static void sens_phis(SensPhis *ph, const Linearization *L, int n, const int *idx, int m, double k)
{
    if (ph->valid && ph->k == k && ph->m == m && memcmp(ph->idx, idx, sizeof(int) * m) == 0) return;
    double A[NMAX * NMAX], P0[NMAX * NMAX];
    for (int a = 0; a < m; a++)
        for (int b = 0; b < m; b++) A[a * m + b] = k * L->Jfull[idx[a] * n + idx[b]];
    solver_phi(m, A, P0, ph->P1, ph->P2, ph->P3);
    ph->valid = 1;
    ph->k = k;
    ph->m = m;
    memcpy(ph->idx, idx, sizeof(int) * m);
}

/* One exponential step of column c over [ta, ta + k] together with the states: z = (u, S) on the block, z' = (f, G)
 * with G = J S + f_p, whose Jacobian [[J, 0], [G_u, J]] carries the states' motion into S exactly where f and G
 * are affine (a lightly damped screw rings at kHz through a step of 30 ms: as a polynomial in time that motion
 * cost S a hundred sub-steps a step, through G_u none). The scheme is exprb32 on z (the states' Jacobian J at
 * the step's start, G_u and the explicit time derivatives at the sub-step's start); S1, the states at the end
 * (ub, the scheme's own: the caller keeps the accepted ones at the step's end) and the error of S's correction
 * against sens_rtol. *done = 0 (nothing changed) when the block is too large for the doubled system: the caller
 * takes sens_substep. */
static int sens_substep_aug(Solver *s, const Linearization *L, int c, double ta, const double *ua, double k,
                            const double *S, double *S1, double *ub, double *err, int *done, char *msg, size_t len)
{
    int n = s->n;
    double G0[NMAX], Gx[NMAX * NMAX], Gt[NMAX];
    *done = 0;
    if (s->sens_aug(s->ctx, c, ta, ua, S, G0, Gx, Gt, msg, len)) return 1;
    int act[NMAX], idx[NMAX], m = 0;
    for (int i = 0; i < n; i++) {
        if (!isfinite(G0[i]) || !isfinite(Gt[i])) {
            snprintf(msg, len, "the sensitivity equations are not finite at t = %.17g (state %d, column %d)", ta, i,
                     c + 1);
            return 1;
        }
        for (int j = 0; j < n; j++)
            if (!isfinite(Gx[i * n + j])) {
                snprintf(msg, len, "the sensitivity equations' Jacobian is not finite at t = %.17g (state %d, "
                         "column %d)", ta, i, c + 1);
                return 1;
            }
        act[i] = L->active[i] || ua[i] != L->u[i] || S[i] != 0.0 || G0[i] != 0.0 || Gt[i] != 0.0;
    }
    for (int changed = 1; changed;) {
        changed = 0;
        for (int j = 0; j < n; j++)
            if (act[j])
                for (int i = 0; i < n; i++)
                    if (!act[i] && (L->Jfull[i * n + j] != 0.0 || Gx[i * n + j] != 0.0)) { act[i] = 1; changed = 1; }
    }
    for (int i = 0; i < n; i++)
        if (act[i]) idx[m++] = i;
    memcpy(S1, S, sizeof(double) * n);
    memcpy(ub, ua, sizeof(double) * n);
    *err = 0.0;
    if (m == 0) { *done = 1; return 0; }
    if (2 * m > NMAX) return 0;
    int m2 = 2 * m;
    /* f and its explicit time derivative at the sub-step's start */
    double f0[NMAX];
    if (ta == L->t && memcmp(ua, L->u, sizeof(double) * n) == 0) memcpy(f0, L->F0, sizeof(double) * n);
    else if (eval_real(s, ta, ua, f0, msg, len)) return 1;
    double M[NMAX * NMAX], P0[NMAX * NMAX], P1[NMAX * NMAX], P2[NMAX * NMAX], P3[NMAX * NMAX];
    for (int a = 0; a < m2 * m2; a++) M[a] = 0.0;
    for (int a = 0; a < m; a++)
        for (int b = 0; b < m; b++) {
            double J = k * L->Jfull[idx[a] * n + idx[b]];
            M[a * m2 + b] = J;
            M[(m + a) * m2 + m + b] = J;
            M[(m + a) * m2 + b] = k * Gx[idx[a] * n + idx[b]];
        }
    solver_phi(m2, M, P0, P1, P2, P3);
    double v0[NMAX], vt[NMAX], y1[NMAX], y2[NMAX], D[NMAX], corr[NMAX];
    for (int a = 0; a < m; a++) {
        v0[a] = f0[idx[a]];
        v0[m + a] = G0[idx[a]];
        vt[a] = L->Ft[idx[a]];
        vt[m + a] = Gt[idx[a]];
    }
    matvec(m2, P1, v0, y1);
    matvec(m2, P2, vt, y2);
    double uU[NMAX], SU[NMAX], fU[NMAX], GU[NMAX];
    memcpy(uU, ua, sizeof(double) * n);
    memcpy(SU, S, sizeof(double) * n);
    for (int a = 0; a < m; a++) {
        uU[idx[a]] += k * y1[a] + k * k * y2[a];
        SU[idx[a]] += k * y1[m + a] + k * k * y2[m + a];
    }
    if (eval_real(s, ta + k, uU, fU, msg, len)) return 1;
    if (s->sens(s->ctx, c, ta + k, uU, SU, GU, msg, len)) return 1;
    /* the defect D = F(z_U) - F(z0) - M (z_U - z0) / k - k F_t, on the block */
    for (int a = 0; a < m; a++) {
        int i = idx[a];
        double du = fU[i] - f0[i] - k * L->Ft[i], dS = GU[i] - G0[i] - k * Gt[i];
        for (int b = 0; b < m; b++) {
            int j = idx[b];
            du -= L->Jfull[i * n + j] * (uU[j] - ua[j]);
            dS -= Gx[i * n + j] * (uU[j] - ua[j]) + L->Jfull[i * n + j] * (SU[j] - S[j]);
        }
        D[a] = du;
        D[m + a] = dS;
    }
    matvec(m2, P3, D, corr);
    memcpy(S1, SU, sizeof(double) * n);
    memcpy(ub, uU, sizeof(double) * n);
    double rt = s->sens_rtol > 0.0 ? s->sens_rtol : s->rtol;
    for (int a = 0; a < m; a++) {
        int i = idx[a];
        ub[i] += 2.0 * k * corr[a];
        double cc = 2.0 * k * corr[m + a];
        S1[i] += cc;
        double sc = rt * fmax(fmax(fmax(fabs(S[i]), fabs(S1[i])), s->Smax[c][i]),
                              s->sens_p[c] > 0.0 ? s->umax[i] / s->sens_p[c] : INFINITY);
        if (sc > 0.0) *err = fmax(*err, fabs(cc) / sc);
    }
    for (int i = 0; i < n; i++)
        if (!isfinite(S1[i])) {
            snprintf(msg, len, "the sensitivities are not finite at t = %.17g (state %d, column %d)", ta + k, i, c + 1);
            return 1;
        }
    *done = 1;
    return 0;
}

/* The columns over the states' accepted step from (t, u0) to (t + h, u1): every column at once (one call of the
 * model's sensitivity equations for all, which share its Jacobian and rates) with one sub-step size; a column whose
 * sub-step misses its tolerance steps with the states (sens_substep_aug) before the sub-step is shortened. */
/* The time of the forward difference of sens_rates, relative to the sub-step (or the motion's time scale). Measured
 * with it for both drives against the generated rates (tests/test_sensitivities.py, every effect at rtol 1e-8): every
 * column's error against central differences the same to three digits; smaller steps lose digits to rounding (the
 * closed form's d y / d F_max: 2e-16 of its largest value with the generated rates, 1.4e-14 here, 1.5e-13 at 1e-4;
 * runs fail at 1e-8). Under a force drive the generated rates stay: with the difference a run cost 5-15 % more
 * (the full model's right-hand side and J^2 a step) where under a prescribed motion it cost 10 % less. */
#define SENS_RATE_STEP 1e-3

/* The fastest time scale of the states' linearised motion, 1 / sqrt(||J^2||) (the infinity norm, on the states
 * that move): for the screw on its spring, 1 / omega (||J|| itself would be c / m, omega squared). */
static double motion_time_scale(const Solver *s, const Linearization *L)
{
    int n = s->n, idx[NMAX], m = 0;
    for (int i = 0; i < n; i++)
        if (L->active[i]) idx[m++] = i;
    double worst = 0.0;
    for (int a = 0; a < m; a++) {
        double row = 0.0;
        for (int b = 0; b < m; b++) {
            double x = 0.0;
            for (int l = 0; l < m; l++) x += L->Jfull[idx[a] * n + idx[l]] * L->Jfull[idx[l] * n + idx[b]];
            row += fabs(x);
        }
        worst = fmax(worst, row);
    }
    return worst > 0.0 ? 1.0 / sqrt(worst) : INFINITY;
}

/* G_t of every column (see above) at (ta, ua): the rate of G = J S + f_p along the states' own motion (u' = f, the
 * inputs at their rates) at fixed S, by a forward difference over a time e = SENS_RATE_STEP min(k, T), T the
 * motion's fastest time scale (a screw ringing at 7 kHz through a sub-step of 30 ms would make a difference over a
 * fraction of the sub-step meaningless): one evaluation of G for all columns and one of f. Its error, e/2 |G_tt|,
 * enters S1 as k^2/6 of it, and the error estimate sees twice that; a second-derivative function of the model in its
 * place cost as much as three evaluations of G and most of the generated code. */
static int sens_rates(Solver *s, double ta, const double *ua, double k, double T, const double (*G0)[NMAX],
                      double (*Gt)[NMAX], char *msg, size_t len)
{
    int n = s->n;
    double f[NMAX], up[NMAX];
    if (s->rhs(s->ctx, ta, ua, f, msg, len)) return 1;
    /* the time step as represented: never below what ta's last digits can show */
    double tp = ta + fmax(SENS_RATE_STEP * fmin(k, T), 1024.0 * DBL_EPSILON * fabs(ta)), e = tp - ta;
    for (int i = 0; i < n; i++) up[i] = ua[i] + e * f[i];
    if (s->sens_all(s->ctx, s->ns, tp, up, (const double (*)[NMAX])s->S, Gt, NULL, msg, len)) return 1;
    for (int c = 0; c < s->ns; c++)
        for (int i = 0; i < n; i++) Gt[c][i] = (Gt[c][i] - G0[c][i]) / e;
    return 0;
}

/* G0 and G_t of every column at the start of a step of the states, from the columns' last sub-step when it ended
 * here, without calling the model. G is affine in S with the model's Jacobian J, which the linearisation L holds
 * exactly at this point, so G(S) = G1 + J (S - S1) for the G1 the last sub-step evaluated at its predicted S1; and
 * along the last sub-step G moved at fixed S by (G(S) - G0(S)) / k0, G0(S) = G0 + J0 (S - S0) at its start (G0, S0
 * and J0 kept): the rate at the middle of the last sub-step rather than here, an error of k0/2 G_tt that the
 * sub-step's error estimate sees as it sees G_tt itself (a sub-step that misses is taken again with the model's own
 * rates). A forward sensitivity run then costs one call of the model's sensitivity equations per sub-step instead
 * of two (under a force drive one of them the generated rates, three times the other). Returns 0 where the history
 * does not apply: no last sub-step ending exactly here (a rejected or an inner sub-step; the inputs jumped, which the
 * model tells by clearing it; a prescribed motion set anew) or one that did not start at a step's start (its J0
 * unknown). The caller has checked that L is the linearisation at (t, u0). */
static int sens_from_history(const Solver *s, const Linearization *L, double t, const double *u0,
                             double (*G0)[NMAX], double (*Gt)[NMAX])
{
    int n = s->n;
    if (!s->sh_valid || !(t > s->sh_t0) || fabs(t - s->sh_t1) > 4.0 * DBL_EPSILON * fmax(1.0, fabs(t))
        || memcmp(s->sh_u1, u0, sizeof(double) * n) != 0)
        return 0;
    double k0 = t - s->sh_t0;
    const double *J = L->Jfull, *J0 = s->sh_J0;
    for (int c = 0; c < s->ns; c++) {
        const double *S = s->S[c];
        double d1[NMAX], d0[NMAX];
        int nz[NMAX], m = 0;
        for (int j = 0; j < n; j++) {
            d1[j] = S[j] - s->sh_S1[c][j];
            d0[j] = S[j] - s->sh_S0[c][j];
            if (d1[j] != 0.0 || d0[j] != 0.0) nz[m++] = j;
        }
        for (int i = 0; i < n; i++) {
            double g = s->sh_G1[c][i], g0 = s->sh_G0[c][i];
            for (int a = 0; a < m; a++) {
                int j = nz[a];
                g += J[i * n + j] * d1[j];
                g0 += J0[i * n + j] * d0[j];
            }
            G0[c][i] = g;
            Gt[c][i] = (g - g0) / k0;
        }
    }
    return 1;
}

static int sens_step(Solver *s, const Linearization *L, double t, const double *u0, double h, const double *u1,
                     char *msg, size_t len)
{
    int n = s->n, ns = s->ns;
    double tau = 0.0, k = h, ua[NMAX], ub[NMAX];
    double S1[SOLVER_SMAX][NMAX], G0[SOLVER_SMAX][NMAX], Gt[SOLVER_SMAX][NMAX], G1[SOLVER_SMAX][NMAX];
    SensPhis ph;
    ph.valid = 0;
    double T = -1.0;   /* the motion's time scale, when the rates are the solver's difference */
    double S1p[SOLVER_SMAX][NMAX];
    int exact = 0;     /* this sub-step takes G0 and G_t from the model, not from the last sub-step */
    memcpy(ua, u0, sizeof(double) * n);
    while (tau < h) {
        k = fmin(k, h - tau);
        int last = tau + k >= h;
        if (last) memcpy(ub, u1, sizeof(double) * n);
        else sens_state_at(s, L, u0, tau + k, ub);
        double ta = t + tau;
        /* at the step's start L holds the exact Jacobian, which the next step's start needs with this one's G0 */
        int at_start = tau == 0.0 && L->t == t && memcmp(L->u, u0, sizeof(double) * n) == 0;
        int from_history = at_start && !exact && sens_from_history(s, L, t, u0, G0, Gt);
        if (!from_history) {
            if (s->sens_rates_given) {
                if (s->sens_all(s->ctx, ns, ta, ua, (const double (*)[NMAX])s->S, G0, Gt, msg, len)) return 1;
            } else {
                if (T < 0.0) T = motion_time_scale(s, L);
                if (s->sens_all(s->ctx, ns, ta, ua, (const double (*)[NMAX])s->S, G0, NULL, msg, len)) return 1;
                if (sens_rates(s, ta, ua, k, T, (const double (*)[NMAX])G0, Gt, msg, len)) return 1;
            }
        }
        int act[NMAX], idx[NMAX], m = 0;
        for (int i = 0; i < n; i++) {
            act[i] = L->active[i];
            for (int c = 0; c < ns; c++) {
                if (!isfinite(G0[c][i]) || !isfinite(Gt[c][i])) {
                    snprintf(msg, len, "the sensitivity equations are not finite at t = %.17g (state %d, column %d)",
                             ta, i, c + 1);
                    return 1;
                }
                act[i] = act[i] || s->S[c][i] != 0.0 || G0[c][i] != 0.0 || Gt[c][i] != 0.0;
            }
        }
        for (int changed = 1; changed;) {
            changed = 0;
            for (int j = 0; j < n; j++)
                if (act[j])
                    for (int i = 0; i < n; i++)
                        if (!act[i] && L->Jfull[i * n + j] != 0.0) { act[i] = 1; changed = 1; }
        }
        for (int i = 0; i < n; i++)
            if (act[i]) idx[m++] = i;
        double err = 0.0, errc[SOLVER_SMAX] = {0.0};
        for (int c = 0; c < ns; c++) memcpy(S1[c], s->S[c], sizeof(double) * n);
        double rt = s->sens_rtol > 0.0 ? s->sens_rtol : s->rtol;
        if (m > 0) {
            sens_phis(&ph, L, n, idx, m, k);
            for (int c = 0; c < ns; c++) {
                double g0[NMAX], gt[NMAX], y1[NMAX], y2[NMAX];
                for (int a = 0; a < m; a++) { g0[a] = G0[c][idx[a]]; gt[a] = Gt[c][idx[a]]; }
                matvec(m, ph.P1, g0, y1);
                matvec(m, ph.P2, gt, y2);
                for (int a = 0; a < m; a++) S1[c][idx[a]] += k * y1[a] + k * k * y2[a];
                memcpy(S1p[c], S1[c], sizeof(double) * n);
            }
            if (s->sens_all(s->ctx, ns, ta + k, ub, (const double (*)[NMAX])S1, G1, NULL, msg, len)) return 1;
            for (int c = 0; c < ns; c++) {
                double D[NMAX], corr[NMAX];
                for (int a = 0; a < m; a++) {
                    int i = idx[a];
                    double d = G1[c][i] - G0[c][i] - k * Gt[c][i];
                    for (int b = 0; b < m; b++) d -= L->Jfull[i * n + idx[b]] * (S1[c][idx[b]] - s->S[c][idx[b]]);
                    D[a] = d;
                }
                matvec(m, ph.P3, D, corr);
                for (int a = 0; a < m; a++) {
                    int i = idx[a];
                    double cc = 2.0 * k * corr[a];
                    S1[c][i] += cc;
                    double sc = rt * fmax(fmax(fmax(fabs(s->S[c][i]), fabs(S1[c][i])), s->Smax[c][i]),
                                          s->sens_p[c] > 0.0 ? s->umax[i] / s->sens_p[c] : INFINITY);
                    if (sc > 0.0) errc[c] = fmax(errc[c], fabs(cc) / sc);
                }
                if (errc[c] > 1.0 && s->sens_aug && !from_history) {
                    /* the states' motion inside the sub-step too fast for a polynomial in time (a ringing):
                     * this column steps with the states */
                    double Sa[NMAX], uba[NMAX], erra;
                    int done;
                    if (sens_substep_aug(s, L, c, ta, ua, k, s->S[c], Sa, uba, &erra, &done, msg, len)) return 1;
                    if (done) {
                        errc[c] = erra;
                        memcpy(S1[c], Sa, sizeof(double) * n);
                    }
                }
                for (int i = 0; i < n; i++)
                    if (!isfinite(S1[c][i])) {
                        snprintf(msg, len, "the sensitivities are not finite at t = %.17g (state %d, column %d)",
                                 ta + k, i, c + 1);
                        return 1;
                    }
                err = fmax(err, errc[c]);
            }
        }
        if (from_history && err > 1.0) { exact = 1; continue; }   /* again, with the model's own G0 and G_t */
        double fac = err > 0.0 ? 0.9 * pow(err, -1.0 / 3.0) : 4.0;
        if (err <= 1.0 || k <= h * 1e-3) {
            /* the next step's start takes G0 and G_t from this sub-step when it ends there and began at this one's */
            s->sh_valid = last && at_start && m > 0;
            if (s->sh_valid) {
                s->sh_t0 = ta;
                s->sh_t1 = t + h;
                memcpy(s->sh_u1, ub, sizeof(double) * n);
                memcpy(s->sh_J0, L->Jfull, sizeof(double) * n * n);
                for (int c = 0; c < ns; c++) {
                    memcpy(s->sh_G1[c], G1[c], sizeof(double) * n);
                    memcpy(s->sh_S1[c], S1p[c], sizeof(double) * n);
                    memcpy(s->sh_G0[c], G0[c], sizeof(double) * n);
                    memcpy(s->sh_S0[c], s->S[c], sizeof(double) * n);
                }
            }
            for (int c = 0; c < ns; c++) {
                memcpy(s->S[c], S1[c], sizeof(double) * n);
                for (int i = 0; i < n; i++) s->Smax[c][i] = fmax(s->Smax[c][i], fabs(S1[c][i]));
            }
            exact = 0;
            tau = last ? h : tau + k;
            memcpy(ua, ub, sizeof(double) * n);
            /* never below the smallest sub-step accepted anyway: a huge error there (a column that blows up across
             * a switch) would otherwise shrink k until tau + k == tau, and the step never ends */
            k = fmax(k * fmin(fac, 4.0), h * 1e-3);
        } else {
            k *= fmax(0.1, fmin(fac, 0.5));
            exact = 1;
        }
    }
    return 0;
}

int solver_init(Solver *s, double t0, const double *u0, char *msg, size_t msglen)
{
    double F[NMAX];
    s->t = t0;
    s->t0 = t0;
    s->pos_int = s->absvel_int = 0.0;
    memcpy(s->u, u0, sizeof(double) * s->n);
    for (int i = 0; i < s->n; i++) s->umax[i] = fabs(u0[i]);
    s->n_steps = s->n_rejected = s->n_rhs = 0;
    s->sh_valid = 0;
    s->fast_off_until = -INFINITY;
    for (int i = 0; i < s->n; i++) s->bal_d[i] = 1.0;
    if (s->h <= 0.0) s->h = 1e-6;
    if (eval_real(s, t0, u0, F, msg, msglen)) return 1;
    s->acc = F[s->ivel];
    s->pos_max = fabs(u0[s->ipos]);
    s->vel_max = fabs(u0[s->ivel]);
    s->t_eq = at_rest(s, u0[s->ivel], s->acc) ? t0 : -1.0;
    return 0;
}

/* ---------------------------------------------------------------- work budget */

static double wall_seconds(void)
{
#ifdef _WIN32
    return (double)GetTickCount64() * 1e-3;
#else
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
#endif
}

typedef struct {
    long attempts;
    double t_start, wall0;
} Budget;

/* 1 (msg filled) once this solver_advance has used up its steps or its seconds: a run the parameters make
 * too fast or too stiff to follow ends in an error that says so, instead of spinning. */
static int over_budget(const Solver *s, Budget *b, double t, double t_end, char *msg, size_t len)
{
    b->attempts++;
    if (s->max_steps > 0 && b->attempts > s->max_steps) {
        double h = s->h_max > 0.0 ? fmin(s->h, s->h_max) : s->h;
        snprintf(msg, len, "work budget used up: %ld internal steps (max_steps) took the solution only from t = %.9g "
                 "to %.9g s of the step to %.9g s (steps of %.3g s); the parameters make the motion too fast to "
                 "follow: check the stiffness, damping and mass (or h_max), or raise max_steps", s->max_steps,
                 b->t_start, t, t_end, h);
        return 1;
    }
    if (s->max_wall_s > 0.0 && (b->attempts & 15) == 0 && wall_seconds() - b->wall0 > s->max_wall_s) {
        snprintf(msg, len, "work budget used up: %.3g s of computing (max_wall_s) after %ld internal steps took the "
                 "solution only from t = %.9g to %.9g s of the step to %.9g s; check the parameters, or raise "
                 "max_wall_s", s->max_wall_s, b->attempts, b->t_start, t, t_end);
        return 1;
    }
    return 0;
}

/* ---------------------------------------------------------------- parts of a step both steppers share */

/* The step to try from t: the proposal, cut at the next kink (*at_bp), at h_max, at the end. 1 (msg) when it
 * underflows. */
static int step_size(const Solver *s, double t, double remaining, double bp, double *h, int *at_bp, char *msg,
                     size_t len)
{
    *h = fmin(s->h, remaining);
    *at_bp = 0;
    if (bp > t && bp - t <= *h) { *h = bp - t; *at_bp = 1; }
    if (s->h_max > 0.0 && *h > s->h_max) { *h = s->h_max; *at_bp = 0; }
    if (*h < 1e-15 * fmax(1.0, fabs(t))) {
        snprintf(msg, len, "step size underflow (h = %g) at t = %.17g: the solution changes too fast to follow; "
                 "check the parameters", *h, t);
        return 1;
    }
    return 0;
}

/* States the trial point U set moving join the active set (their columns filled). 1 when it grew. */
static int expand_active(Solver *s, Linearization *L, const double *FU)
{
    int n = s->n, expanded = 0;
    for (int i = 0; i < n; i++)
        if (!L->active[i] && FU[i] != 0.0) { L->active[i] = 1; expanded = 1; }
    if (!expanded) return 0;
    int filled[NMAX];
    for (int i = 0; i < n; i++) filled[i] = 0;
    for (int a = 0; a < L->k; a++) filled[L->idx[a]] = 1;
    close_active_set(s, L, filled);
    return 1;
}

/* D = F(U) - F0 - J (U - u) - h Ft on the active block; returns 1 when D vanished (the step was linear). The
 * part of D within the rounding error of evaluating F is noise, not nonlinearity: without this the error
 * estimate of a stiff linear element never lets the step grow. */
static int defect(const Solver *s, const Linearization *L, double h, const double *U, const double *FU, double *D)
{
    int n = s->n, k = L->k, linear = 1;
    for (int a = 0; a < k; a++) {
        int i = L->idx[a];
        double d = FU[i] - L->F0[i] - h * L->Ft[i];
        double mag = fabs(FU[i]) + fabs(L->F0[i]) + fabs(h * L->Ft[i]);
        for (int b = 0; b < k; b++) {
            int j = L->idx[b];
            d -= L->J[i * n + j] * (U[j] - s->u[j]);
            mag += fabs(L->J[i * n + j]) * (fabs(U[j]) + fabs(s->u[j]));
        }
        double noise = 16.0 * DBL_EPSILON * mag;
        D[a] = fabs(d) <= noise ? 0.0 : d - copysign(noise, d);
        if (D[a] != 0.0) linear = 0;
    }
    return linear;
}

/* u1 = U + 2h corr on the active block; the error of the correction against the tolerance. */
static double correct(const Solver *s, const Linearization *L, double h, const double *corr, double *u1)
{
    double err = 0.0;
    for (int a = 0; a < L->k; a++) {
        int i = L->idx[a];
        double c = 2.0 * h * corr[a];
        u1[i] += c;
        double sc = s->rtol * fmax(fmax(fabs(s->u[i]), fabs(u1[i])), s->umax[i]) + s->atol;
        err = fmax(err, fabs(c) / sc);
    }
    return err;
}

/* The derivative carried where it agrees with the evaluated one within rounding (as linearize does). */
static double carried(double evaluated, double carried_value, double mag)
{
    return fabs(evaluated - carried_value) <= 8.0 * DBL_EPSILON * mag ? carried_value : evaluated;
}

/* After a linear step that reached no kink with the same active set, the Jacobian and F_t at its end point are
 * those of its start: L moves to (s->t, u1) with the derivative from F(U) = F(u1), or the carried one where the
 * two agree within rounding. */
static void reuse_linearization(const Solver *s, Linearization *L, const double *u1, const double *FU)
{
    int n = s->n, k = L->k;
    L->t = s->t;
    memcpy(L->u, u1, sizeof(double) * n);
    for (int a = 0; a < k; a++) {
        int i = L->idx[a];
        double mag = fabs(FU[i]);
        for (int b = 0; b < k; b++) mag += fabs(L->J[i * n + L->idx[b]] * u1[L->idx[b]]);
        L->F0[i] = carried(FU[i], s->z[i], mag);
    }
}

/* ---------------------------------------------------------------- steps without dense samples
 *
 * When the model declares the (position, velocity) block linear (lin2: force-driven, no table, no effect) but
 * other states move too (the 6-DOF load case), the monitored block is the damped oscillator
 *     y' = v,  v' = -k y - g v + f(t),
 * whose forcing f carries the load and the (small, smooth) coupling to the other states. Its monitors come
 * from the closed form of that oscillator on each step with f affine, fitted to the step's two ends, exactly
 * as the axial pullout's pieces (piece_monitors): no dense samples, so the step is set by the error estimate of
 * the method alone. The closed form must reproduce the integrator's end of the step (y, v) to the dense-output
 * tolerance, otherwise the step is rejected: where the coupling is strong (large rotations, an interaction
 * point off the axis) the steps shrink until an affine forcing holds, and the monitors keep their accuracy.
 * Without monitors (monitors = false) nothing between steps is needed at all. Either way the phi functions are
 * applied to vectors by the squaring ladder (PhiVec). */

/* One accepted step from (s->t, s->u) with the linearisation L. Returns 0 when a step was taken, 1 on an
 * error, -1 when this step needs the dense stepper (nothing changed but the proposed step size). *reuse is set
 * when the step was linear, as in the dense stepper. */
static int fast_step(Solver *s, Linearization *L, double t_end, double bp, Budget *budget, int *reuse,
                     char *msg, size_t msglen)
{
    int n = s->n, ip = s->ipos, iv = s->ivel;
    double t = s->t, remaining = t_end - t;
    int follow = s->monitors;
    double kk = 0.0, gg = 0.0;
    if (follow) {
        if (!s->lin2 || L->J[ip * n + ip] != 0.0 || L->J[ip * n + iv] != 1.0) return -1;
        kk = -L->J[iv * n + ip];
        gg = -L->J[iv * n + iv];
        if (!(kk > 0.0) || !(gg >= 0.0) || !isfinite(kk) || !isfinite(gg)) return -1;
    }
    if (!s->work) return -1;
    PhiVec *PV = s->work;
    double A[NMAX * NMAX];
    int expanded_any = 0, prepared = 0;
    for (int first = 1;; first = 0) {
        if (!first && over_budget(s, budget, t, t_end, msg, msglen)) return 1;
        double h;
        int at_bp;
        if (step_size(s, t, remaining, bp, &h, &at_bp, msg, msglen)) return 1;
        int k = L->k;
        if (!prepared) {
            /* the balancing of the last step's Jacobian is the guess for this one's (by state) */
            double guess[NMAX];
            active_block(s, L, 1.0, A);
            for (int a = 0; a < k; a++) guess[a] = s->bal_d[L->idx[a]];
            phivec_prepare(PV, k, A, guess);
            for (int a = 0; a < k; a++) s->bal_d[L->idx[a]] = guess[a];
            prepared = 1;
        }
        if (phivec_build(PV, h)) return -1;
        /* U = u + h phi1 F0 + h^2 phi2 Ft, and the derivative of the linearised solution zU = phi0 F0 + h phi1 Ft */
        double F0a[NMAX], Fta[NMAX], p0F[NMAX], p1F[NMAX], p1T[NMAX], p2T[NMAX];
        int has_ft = 0;
        for (int a = 0; a < k; a++) {
            F0a[a] = L->F0[L->idx[a]];
            Fta[a] = L->Ft[L->idx[a]];
            if (Fta[a] != 0.0) has_ft = 1;
        }
        double *pF[4] = {p0F, p1F, NULL, NULL};
        phivec_apply(PV, F0a, 1, pF);
        if (has_ft) {
            double *pT[4] = {NULL, p1T, p2T, NULL};
            phivec_apply(PV, Fta, 2, pT);
        } else {
            for (int a = 0; a < k; a++) p1T[a] = p2T[a] = 0.0;
        }
        double U[NMAX], FU[NMAX], zU[NMAX];
        memcpy(U, s->u, sizeof(double) * n);
        memcpy(zU, L->F0, sizeof(double) * n);
        for (int a = 0; a < k; a++) {
            int i = L->idx[a];
            U[i] += h * p1F[a] + h * h * p2T[a];
            zU[i] = p0F[a] + h * p1T[a];
        }
        if (eval_real(s, t + h, U, FU, msg, msglen)) return 1;
        int grown = expand_active(s, L, FU);
        if (grown) { expanded_any = 1; prepared = 0; continue; }
        /* correction 2h phi3 D (as the dense stepper) */
        double D[NMAX], p3D[NMAX], u1[NMAX];
        int linear = defect(s, L, h, U, FU, D);
        memcpy(u1, U, sizeof(double) * n);
        double err = 0.0;
        if (!linear) {
            double *pD[4] = {NULL, NULL, NULL, p3D};
            phivec_apply(PV, D, 3, pD);
            err = correct(s, L, h, p3D, u1);
        }
        double fac_e = err > 0.0 ? 0.9 * pow(err, -1.0 / 3.0) : 10.0;
        /* the monitored block: the oscillator with an affine forcing through both ends of the step */
        double rd = 0.0, F1[NMAX], a1 = zU[iv];
        Piece P;
        double yH = 0.0, vH = 0.0, aH = 0.0, yint = 0.0;
        PieceMonitors mon = {s->pos_max, s->vel_max, 0.0, 0.0, s->t_eq};
        if (follow && err <= 1.0) {
            if (linear) memcpy(F1, FU, sizeof(double) * n);
            else if (eval_real(s, t + h, u1, F1, msg, msglen)) return 1;
            double mag = fabs(F1[iv]);
            for (int a = 0; a < k; a++) mag += fabs(L->J[iv * n + L->idx[a]] * u1[L->idx[a]]);
            a1 = carried(F1[iv], zU[iv], mag);
            double y0 = s->u[ip], v0 = s->u[iv], a0 = L->F0[iv], y1 = u1[ip], v1 = u1[iv];
            double df = (a1 - a0) + gg * (v1 - v0) + kk * (y1 - y0);   /* f(t + h) - f(t) */
            P = (Piece){kk, gg, y0, v0, a0, df / h};
            piece_exact(&P, h, &yH, &vH, &aH, &yint);
            double rtol_d = s->rtol;
            double pscale = fmax(fmax(s->pos_max, s->eps_v * h), fmax(fabs(y0), fabs(y1)));
            double vscale = fmax(fmax(s->vel_max, s->eps_v), fmax(fabs(v0), fabs(v1)));
            rd = fmax(fabs(yH - y1) / (rtol_d * pscale), fabs(vH - v1) / (rtol_d * vscale));
            if (!(rd <= 1.0)) rd = isfinite(rd) ? rd : 1e30;
            else if (piece_monitors(s, &P, h, yH, vH, aH, yint, &mon)) {
                /* too many roots (a ringing the closed form cannot enumerate): the dense stepper takes the rest
                 * of this load piece */
                s->fast_off_until = bp > t ? bp : t_end;
                return -1;
            }
        }
        double fac_d = rd > 0.0 ? 0.9 * pow(rd, -1.0 / 3.0) : 10.0;
        double fac = fmin(fmin(fac_e, fac_d), 10.0);
        if (!(err <= 1.0 && rd <= 1.0)) {
            /* the closed form misses where the forcing is not affine over the step, a fast transient of the
             * coupling (the first microseconds of a suddenly applied lateral load): its mismatch falls slowly
             * with h until the step resolves the transient, so halve at least */
            s->n_rejected++;
            s->h = h * fmax(0.1, fmin(fac, rd > 1.0 ? 0.5 : 0.9));
            continue;
        }
        /* accepted */
        if (follow) {
            take_piece_monitors(s, &mon);
            /* the closed form's end is within the dense tolerance of u1; keep both extremes */
            s->pos_max = fmax(s->pos_max, fabs(u1[ip]));
            s->vel_max = fmax(s->vel_max, fabs(u1[iv]));
            if (!at_rest(s, u1[iv], a1)) s->t_eq = -1.0;
        }
        for (int i = 0; i < n; i++) s->umax[i] = fmax(s->umax[i], fabs(u1[i]));
        double u0[NMAX];
        memcpy(u0, s->u, sizeof(double) * n);
        memcpy(s->u, u1, sizeof(double) * n);
        s->t = (h == remaining) ? t_end : (at_bp ? bp : t + h);
        if (s->ns && sens_step(s, L, t, u0, s->t - t, u1, msg, msglen)) return 1;
        s->acc = follow ? a1 : zU[iv];
        memcpy(s->z, zU, sizeof(double) * n);
        s->z[iv] = s->acc;
        s->z_valid = 1;
        s->n_steps++;
        if (linear && !at_bp && !expanded_any) {
            reuse_linearization(s, L, u1, FU);
            *reuse = 1;
        }
        s->h = (h < s->h && fac >= 1.0) ? fmax(s->h, h * fac) : h * fac;
        return 0;
    }
}

int solver_advance(Solver *s, double t_end, char *msg, size_t msglen)
{
    Budget budget = {0, s->t, s->max_wall_s > 0.0 ? wall_seconds() : 0.0};
    int n = s->n;
    Linearization L;
    Phis P;
    double A[NMAX * NMAX];
    int reuse = 0;   /* the last step was exactly linear: its Jacobian holds at its end point */
    while (s->t < t_end) {
        double t = s->t;
        double remaining = t_end - t;
        if (remaining <= 1e-14 * fmax(1.0, fabs(t_end))) { s->t = t_end; break; }
        if (over_budget(s, &budget, t, t_end, msg, msglen)) return 1;
        if (!reuse && linearize(s, t, s->u, &L, msg, msglen)) return 1;
        reuse = 0;
        if (L.k == 0) {              /* at rest with no load: nothing moves until the next kink */
            double bp = s->breakpoint(s->ctx, t);
            while (bp - t <= 1e-12 * fmax(1.0, fabs(t))) bp = s->breakpoint(s->ctx, bp);
            s->t = fmin(t_end, bp);
            if (s->ns && sens_step(s, &L, t, s->u, s->t - t, s->u, msg, msglen)) return 1;
            s->pos_int += (s->t - t) * s->u[s->ipos];
            s->absvel_int += (s->t - t) * fabs(s->u[s->ivel]);
            s->acc = 0.0;
            if (s->t_eq < 0.0 && at_rest(s, s->u[s->ivel], 0.0)) s->t_eq = t;
            continue;
        }
        double bp = s->breakpoint(s->ctx, t);
        /* a communication point a rounding error short of a kink (0.05 reached as 0.049999999999999996):
         * take the kink as passed rather than a step of 1e-17 s */
        double skipped = -1.0;
        while (bp - t <= 1e-12 * fmax(1.0, fabs(t))) { skipped = bp; bp = s->breakpoint(s->ctx, bp); }
        if (s->lin2) {   /* a linear 2-state block: one exact step to the next kink or the end */
            double t_next = (bp > t && bp - t < remaining) ? bp : t_end;
            /* a kink passed within rounding: the load's slope is the one after it */
            if (skipped > t && linearize(s, skipped, s->u, &L, msg, msglen)) return 1;
            int r = linear_piece(s, &L, t_next - t, t_next, msg, msglen);
            if (r > 0) return 1;
            if (r == 0) continue;
            if (skipped > t && linearize(s, t, s->u, &L, msg, msglen)) return 1;
        }
        if ((s->lin2 || !s->monitors) && !(t < s->fast_off_until)) {   /* no dense samples needed: fast_step */
            int r = fast_step(s, &L, t_end, bp, &budget, &reuse, msg, msglen);
            if (r > 0) return 1;
            if (r == 0) continue;
        }
        int expanded_any = 0;
        for (int first = 1;; first = 0) {
            if (!first && over_budget(s, &budget, t, t_end, msg, msglen)) return 1;
            double h;
            int at_bp;
            if (step_size(s, t, remaining, bp, &h, &at_bp, msg, msglen)) return 1;
            int k = L.k;
            active_block(s, &L, h, A);
            phi_pair(k, A, P.phs, P.phf);
            P.h = h;
            /* U = u + h phi1 F0 + h^2 phi2 Ft */
            double U[NMAX], FU[NMAX], zU[NMAX];
            propagate_linear(s, &L, s->u, L.F0, h, P.phf, U, zU);
            if (eval_real(s, t + h, U, FU, msg, msglen)) return 1;
            int grown = expand_active(s, &L, FU);
            if (grown) { expanded_any = 1; continue; }
            /* correction 2h phi3 D */
            double D[NMAX], corr[NMAX], u1[NMAX];
            int linear = defect(s, &L, h, U, FU, D);
            matvec(k, P.phf[3], D, corr);
            memcpy(u1, U, sizeof(double) * n);
            double err = correct(s, &L, h, corr, u1);
            /* dense samples of the linearised solution, blended to end at u1 */
            double w[NSUB + 1][NMAX], zs[NSUB + 1][NMAX], ac[NSUB + 1];
            double dt = h / NSUB;
            memcpy(w[0], s->u, sizeof(double) * n);
            memcpy(zs[0], L.F0, sizeof(double) * n);
            for (int j = 1; j <= NSUB; j++) propagate_linear(s, &L, w[j - 1], zs[j - 1], dt, P.phs, w[j], zs[j]);
            double gap[NMAX];
            for (int i = 0; i < n; i++) gap[i] = u1[i] - w[NSUB][i];
            for (int j = 0; j <= NSUB; j++) {
                for (int i = 0; i < n; i++) w[j][i] += gap[i] * j / (double)NSUB;
                ac[j] = zs[j][s->ivel];
            }
            /* odd samples against the Hermite cubic of their neighbours */
            /* floors: the monitors need v only to a fraction of the equilibrium threshold, and y to
             * what that velocity moves in a step */
            double pscale = fmax(s->pos_max, s->eps_v * h), vscale = fmax(s->vel_max, s->eps_v);
            for (int j = 0; j <= NSUB; j++) {
                pscale = fmax(pscale, fabs(w[j][s->ipos]));
                vscale = fmax(vscale, fabs(w[j][s->ivel]));
            }
            double rtol_d = fmin(1e-7, 100.0 * s->rtol);   /* dense output: never looser than 1e-7 */
            double rd = 0.0;
            for (int j = 1; j < NSUB && s->monitors; j += 2) {
                double p0 = w[j - 1][s->ipos], p1 = w[j + 1][s->ipos];
                double v0 = w[j - 1][s->ivel], v1 = w[j + 1][s->ivel];
                double ph = 0.5 * (p0 + p1) + 2.0 * dt * (v0 - v1) / 8.0;
                double vh = 0.5 * (v0 + v1) + 2.0 * dt * (ac[j - 1] - ac[j + 1]) / 8.0;
                if (pscale > 0.0) rd = fmax(rd, fabs(ph - w[j][s->ipos]) / (rtol_d * pscale));
                if (vscale > 0.0) rd = fmax(rd, fabs(vh - w[j][s->ivel]) / (rtol_d * vscale));
            }
            double fac_e = err > 0.0 ? 0.9 * pow(err, -1.0 / 3.0) : 10.0;
            double fac_d = rd > 0.0 ? 0.9 * pow(rd, -0.25) : 10.0;
            double fac = fmin(fmin(fac_e, fac_d), 10.0);
            if (!(err <= 1.0 && rd <= 1.0)) {
                s->n_rejected++;
                s->h = h * fmax(0.1, fmin(fac, 0.9));
                continue;
            }
            /* accepted: monitors over the samples */
            for (int j = 0; j < NSUB && s->monitors; j++) {
                double p0 = w[j][s->ipos], p1 = w[j + 1][s->ipos];
                double v0 = w[j][s->ivel], v1 = w[j + 1][s->ivel];
                /* integrals on the Hermite pieces (exact for cubics); |v| across a sign change by
                 * splitting the piece at the linear root */
                s->pos_int += 0.5 * dt * (p0 + p1) + dt * dt * (v0 - v1) / 12.0;
                if (v0 * v1 >= 0.0)
                    s->absvel_int += fabs(0.5 * dt * (v0 + v1) + dt * dt * (ac[j] - ac[j + 1]) / 12.0);
                else
                    s->absvel_int += 0.5 * dt * (v0 * v0 + v1 * v1) / (fabs(v0) + fabs(v1));
                s->pos_max = fmax(s->pos_max, hermite_absmax(p0, v0, p1, v1, dt));
                s->vel_max = fmax(s->vel_max, hermite_absmax(v0, ac[j], v1, ac[j + 1], dt));
                int r1 = at_rest(s, v1, ac[j + 1]);
                if (!r1) {
                    s->t_eq = -1.0;
                } else if (s->t_eq < 0.0) {
                    double g0 = fmax(fabs(v0) / s->eps_v, fabs(ac[j]) / s->eps_a) - 1.0;
                    double g1 = fmax(fabs(v1) / s->eps_v, fabs(ac[j + 1]) / s->eps_a) - 1.0;
                    s->t_eq = t + j * dt + (g0 > 0.0 ? locate_rest(s, &L, w[j], zs[j], dt, g0, g1) : 0.0);
                }
            }
            if (s->monitors && s->t_eq >= 0.0) {
                double s_c = fmax(0.0, s->t_eq - t);
                double s_new = rest_after_oscillation(s, &L, w[0], zs[0], h, s_c);
                if (s_new > s_c) s->t_eq = t + s_new;
            }
            for (int i = 0; i < n; i++) s->umax[i] = fmax(s->umax[i], fabs(u1[i]));
            double u0[NMAX];
            memcpy(u0, s->u, sizeof(double) * n);
            memcpy(s->u, u1, sizeof(double) * n);
            s->t = (h == remaining) ? t_end : (at_bp ? bp : t + h);
            if (s->ns && sens_step(s, &L, t, u0, s->t - t, u1, msg, msglen)) return 1;
            s->acc = ac[NSUB];
            /* carry the derivative: exact for the linearised model, blended like the state */
            memcpy(s->z, zs[NSUB], sizeof(double) * n);
            s->z_valid = 1;
            s->n_steps++;
            /* a linear step that reached no kink with the same active set: its linearisation holds at its end */
            if (linear && !at_bp && !expanded_any) {
                reuse_linearization(s, &L, u1, FU);
                reuse = 1;
            }
            /* a step shortened by a kink or the end keeps the earlier proposal when it went well */
            s->h = (h < s->h && fac >= 1.0) ? fmax(s->h, h * fac) : h * fac;
            break;
        }
    }
    return 0;
}
