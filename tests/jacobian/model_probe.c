/* A probe into the FMU's model for tests/test_jacobian.py: the right-hand side, Jacobian and time derivative
 * that the solver receives, at any state, from the very sources the FMU is built from (model.c with the
 * C generated from the Modelica). Compiled by the test against build/fmu/sources. */
#include "model.c"

static ModelInstance probe;   /* one instance per loaded copy of this test library */

int probe_n_vr(void) { return N_VR; }

/* Set every variable by value reference (v has N_VR entries, index = value reference), initialise. */
int probe_init(const double *v, char *msg, int len)
{
    model_free(&probe);
    model_set_start_values(&probe);
    for (int i = 1; i < N_VR; i++) probe.v[i] = v[i];
    if (model_validate(&probe, msg, (size_t)len)) return 1;
    return model_initialize(&probe, 0.0, msg, (size_t)len);
}

int probe_lin(double t, const double *x, double *du, double *J, double *Ft, char *msg, int len)
{
    return lin(&probe, t, x, du, J, Ft, msg, (size_t)len);
}

int probe_lin2(void) { return probe.solver.lin2; }
