/* The InterfaceElement model: its variables, instance and equations (element.c). The FMI layer (fmu/fmi2.c,
 * shared with ScrewVertebra) calls only what is declared here. */
#ifndef MODEL_H
#define MODEL_H

#include <stddef.h>

typedef enum { TYPE_REAL, TYPE_INTEGER, TYPE_BOOLEAN } VarType;
typedef enum { CAUS_PARAMETER, CAUS_CALCULATED, CAUS_INPUT, CAUS_OUTPUT, CAUS_LOCAL } Causality;

#include "variables.h"
#include "el_model.h"

#define MODEL_NAME "InterfaceElement"
/* Interfaces beyond co-simulation: model exchange, and getting and setting the FMU state (the instance holds
 * no pointers, so a state is a copy of it). */
#define MODEL_ME 1
#define MODEL_FMU_STATE 1

typedef struct {
    const char *name;
    int vr;
    VarType type;
    Causality causality;
    double start;
} VarInfo;

const VarInfo *model_variable(unsigned int vr);

enum { NX = EL_NX };

typedef struct ModelInstance {
    double v[N_VR];          /* every variable by value reference (Boolean as 0/1) */
    double dv[N_VR];         /* first derivatives of the inputs (fmi2SetRealInputDerivatives, co-simulation) */
    double t_inputs;         /* time at which the inputs and their derivatives apply */
    double time;
    double x[NX];            /* the states z_y, z_f, F_ve, kappa (el_model.h's order) */
    double p[EL_NP];
    double d[EL_ND];
    int iw[EL_SZ_IW];
    double w[EL_SZ_W];
    double scale[NX];        /* running max |x_i| (with a floor): the scale of the error control */
    int dirty;               /* inputs, states or time changed since the outputs were computed */
    long n_steps, n_rejected;
} ModelInstance;

void model_set_start_values(ModelInstance *mi);
void model_free(ModelInstance *mi);
int model_validate(const ModelInstance *mi, char *msg, size_t msglen);
int model_initialize(ModelInstance *mi, double t0, char *msg, size_t msglen);
/* Co-simulation: integrate the states from mi->time to t_end (inputs affine in time with their derivatives). */
int model_do_step(ModelInstance *mi, double t_end, char *msg, size_t msglen);
/* The outputs (and the states' rates) at the current time, inputs and states, when something changed. */
void model_refresh(ModelInstance *mi);
#define MODEL_TOUCH(mi) ((mi)->dirty = 1)
/* The co-simulation integrator's statistics, for the log at fmi2Terminate */
#define MODEL_N_STEPS(mi) ((mi)->n_steps)
#define MODEL_N_REJECTED(mi) ((mi)->n_rejected)
#define MODEL_N_RHS(mi) (2 * ((mi)->n_steps + (mi)->n_rejected))
/* Model exchange: the states and their rates. */
void model_get_states(const ModelInstance *mi, double *x);
void model_set_states(ModelInstance *mi, const double *x);
int model_derivatives(ModelInstance *mi, double *dx, char *msg, size_t msglen);

#endif
