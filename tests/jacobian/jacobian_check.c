/* The closed-form Jacobian columns of fmu/model.c (jacobian_columns) against the complex step of the same
 * right-hand side, at random states with large angles, an interaction point off the axis and the centre of
 * gravity off it, and random loads. Prints the worst column-relative difference and the count of columns.
 * Built and run by tests/test_jacobian.py. Usage: jacobian_check trials seed */
#include "model.c"

#include <stdlib.h>

static double rnd(void) { return rand() / (double)RAND_MAX * 2.0 - 1.0; }

int main(int argc, char **argv)
{
    int trials = argc > 1 ? atoi(argv[1]) : 1000;
    srand(argc > 2 ? (unsigned)atoi(argv[2]) : 1u);
    static ModelInstance mi;
    char msg[256];
    double worst = 0.0;
    long columns = 0;
    for (int trial = 0; trial < trials; trial++) {
        model_set_start_values(&mi);
        mi.v[VR_c_x] = 1e5 * exp(3 * rnd()); mi.v[VR_c_y] = 1e6 * exp(3 * rnd()); mi.v[VR_c_z] = 1e5 * exp(3 * rnd());
        mi.v[VR_d_x] = 100 * exp(2 * rnd()); mi.v[VR_d_y] = 300 * exp(2 * rnd()); mi.v[VR_d_z] = 200 * exp(2 * rnd());
        mi.v[VR_c_alpha] = 10 * exp(2 * rnd()); mi.v[VR_c_beta] = exp(2 * rnd()); mi.v[VR_c_gamma] = 10 * exp(2 * rnd());
        mi.v[VR_d_alpha] = 0.01 * exp(2 * rnd()); mi.v[VR_d_beta] = 0.01 * exp(2 * rnd());
        mi.v[VR_d_gamma] = 0.01 * exp(2 * rnd());
        mi.v[VR_cg_x] = 0.0003 * rnd(); mi.v[VR_cg_y] = -0.007 + 0.002 * rnd(); mi.v[VR_cg_z] = 0.0003 * rnd();
        mi.v[VR_rI_x] = 0.0005 * rnd(); mi.v[VR_rI_z] = 0.0005 * rnd(); mi.v[VR_phi_inertia] = 0.3 * rnd();
        mi.v[VR_F_max] = 411; mi.v[VR_t_ramp] = 0.05;
        if (model_validate(&mi, msg, sizeof msg) || model_initialize(&mi, 0.0, msg, sizeof msg)) {
            printf("error %s\n", msg);
            return 1;
        }
        mi.v[VR_F_ext_x] = 20 * rnd(); mi.v[VR_F_ext_y] = 20 * rnd(); mi.v[VR_F_ext_z] = 10 * rnd();
        mi.v[VR_T_ext_x] = 0.005 * rnd(); mi.v[VR_T_ext_y] = 0.005 * rnd(); mi.v[VR_T_ext_z] = 0.005 * rnd();
        double u[NX] = {0}, scale = trial % 2 ? 1.0 : 0.01;   /* angles up to 1 rad, or 10 mrad */
        for (int i = 0; i < 2 * NQ; i++) u[i] = (i < 3 ? 1e-4 : i < 6 ? scale : i < 9 ? 1e-2 : 20.0) * rnd();
        double t = 0.05 * (rnd() + 1.0), J[NX * NX] = {0};
        int filled[NX] = {0};
        jacobian_columns(&mi, t, u, J, filled);
        for (int j = 0; j < NX; j++) {
            if (!filled[j]) continue;
            cplx uc[NX], du[NX];
            for (int i = 0; i < NX; i++) uc[i] = u[i];
            uc[j] += I * 1e-100;
            if (rhs(&mi, t, uc, du, msg, sizeof msg)) { printf("error %s\n", msg); return 1; }
            double colmax = 0.0;
            for (int i = 0; i < NX; i++) colmax = fmax(colmax, fabs(cimag(du[i]) / 1e-100));
            for (int i = 0; i < NX; i++) {
                double e = fabs(J[i * NX + j] - cimag(du[i]) / 1e-100) / (colmax > 0 ? colmax : 1.0);
                if (e > worst) worst = e;
            }
            columns++;
        }
    }
    printf("%.17g %ld\n", worst, columns);
    return 0;
}
