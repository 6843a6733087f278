/* The ScrewVertebra model: its variables, instance and equations (model.c). The FMI layer (fmi2.c)
 * calls only the functions declared here. */
#ifndef MODEL_H
#define MODEL_H

#include <stddef.h>

typedef enum { TYPE_REAL, TYPE_INTEGER, TYPE_BOOLEAN } VarType;
typedef enum { CAUS_PARAMETER, CAUS_CALCULATED, CAUS_INPUT, CAUS_OUTPUT, CAUS_LOCAL } Causality;

#include "variables.h"
#include "solver.h"
#include "sv_model.h"

#define MODEL_NAME "ScrewVertebra"
/* Co-simulation only (its own solver), without getting and setting the FMU state. A build with
 * -DMODEL_FMU_STATE=1 (the split-body tests) gets and sets it as a copy of the instance: the one pointer in
 * it, the solver's workspace, is scratch that no state depends on. */
#define MODEL_ME 0
#ifndef MODEL_FMU_STATE
#define MODEL_FMU_STATE 0
#endif

typedef struct {
    const char *name;
    int vr;
    VarType type;
    Causality causality;
    double start;
} VarInfo;

/* The variable table (generated from modelica/ScrewVertebra.mo); vr -> entry, NULL for unknown vr. */
const VarInfo *model_variable(unsigned int vr);

/* The solver's states, in the order of the generated model (sv_model.h): the six coordinates, their rates,
 * then the states of the axial effects (MODEL.md). */
enum { NX = SV_NX };

typedef int (*sv_function)(const double **arg, double **res, int *iw, double *w, int mem);

typedef struct ModelInstance {
    double v[N_VR];          /* every variable by value reference (Integer and Boolean as 0/1 doubles) */
    double dv[N_VR];         /* first derivatives of the inputs (fmi2SetRealInputDerivatives) */
    double t_inputs;         /* time at which the inputs and their derivatives apply */
    double inputs_end[SV_NU]; /* the inputs at the end of the last communication step, as they were extrapolated */
    int inputs_end_valid;
    double time;
    double u[NX];
    double p[SV_NP];         /* the parameters, in the generated functions' order (set at initialisation) */
    double d[SV_ND];         /* the derived parameters (sv_derived) */
    double kinks[SV_NKINKS]; /* times at which the load has a kink (sv_kinks) */
    sv_function f_rhs, f_lin, f_out, f_drive;   /* the variant the parameters call for (f_drive: motion only) */
    /* forward sensitivities: the selected parameters' columns (sens_p[k]), their unit directions in p, and the
     * full variant's sensitivity functions (NULL: none selected) */
    int n_sens;
    int sens_col[SV_NSENS];  /* k of sens_p[k] (0-based) of each solver column */
    double E[SV_NSENS][SV_NP];
    sv_function f_sens_rhs, f_sens_lin_all, f_sens_rhs_all, f_sens_aug, f_sens_out, f_sens_drive;
    int iw[SV_SZ_IW];        /* work arrays of the generated functions */
    double w[SV_SZ_W];
    Solver solver;
    void *work;              /* the solver's workspace (solver_work_size bytes), made once, kept across resets */
} ModelInstance;

/* All variables to their start values (the workspace is kept). */
void model_set_start_values(ModelInstance *mi);

/* Free what the instance holds (its workspace). */
void model_free(ModelInstance *mi);

/* 0 when every parameter is valid; otherwise 1 with msg naming the parameter and the fix. */
int model_validate(const ModelInstance *mi, char *msg, size_t msglen);

/* Compute calculated parameters, put the screw at rest, start the solver and fill the outputs. */
int model_initialize(ModelInstance *mi, double t0, char *msg, size_t msglen);

/* Advance from mi->time to t_end and update the outputs. */
int model_do_step(ModelInstance *mi, double t_end, char *msg, size_t msglen);

/* The outputs are computed by each step: nothing to refresh when inputs change between steps. */
static inline void model_refresh(ModelInstance *mi) { (void)mi; }
#define MODEL_TOUCH(mi) ((void)(mi))
/* The solver's statistics, for the log at fmi2Terminate */
#define MODEL_N_STEPS(mi) ((mi)->solver.n_steps)
#define MODEL_N_REJECTED(mi) ((mi)->solver.n_rejected)
#define MODEL_N_RHS(mi) ((mi)->solver.n_rhs)

#endif
