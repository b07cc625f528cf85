/* Bulk access to an acados OCP solver: one call per phase of the real-time iteration instead of one
 * call per stage and field from Python (hvac_mpc.mpc.rti_acados). Only acados' C interface is used. */
typedef void *P;
extern void ocp_nlp_out_set(P config, P dims, P out, int stage, const char *field, void *value);
extern void ocp_nlp_out_get(P config, P dims, P out, int stage, const char *field, void *value);
extern int ocp_nlp_cost_model_set(P config, P dims, P in, int stage, const char *field, void *value);
extern int ocp_nlp_constraints_model_set(P config, P dims, P in, int stage, const char *field, void *value);
extern void ocp_nlp_solver_opts_set(P config, P opts, const char *field, void *value);
extern int ocp_nlp_solve(P solver, P in, P out);
extern void ocp_nlp_get(P config, P solver, const char *field, void *value);

typedef struct {
    P config, dims, in, out, solver, opts, capsule;
    int (*update_params)(P capsule, int stage, double *p, int np);
    int N, nx, nu, ny, ny_e, np;
} hvac_ocp;

/* primal iterate: X (N+1, nx), U (N, nu), row major */
void hvac_set_iterate(const hvac_ocp *o, double *X, double *U)
{
    for (int k = 0; k <= o->N; k++) ocp_nlp_out_set(o->config, o->dims, o->out, k, "x", X + k * o->nx);
    for (int k = 0; k < o->N; k++) ocp_nlp_out_set(o->config, o->dims, o->out, k, "u", U + k * o->nu);
}

void hvac_get_iterate(const hvac_ocp *o, double *X, double *U)
{
    for (int k = 0; k <= o->N; k++) ocp_nlp_out_get(o->config, o->dims, o->out, k, "x", X + k * o->nx);
    for (int k = 0; k < o->N; k++) ocp_nlp_out_get(o->config, o->dims, o->out, k, "u", U + k * o->nu);
}

/* references yref (N, ny) and yref_e (ny_e); weights W (N, ny*ny) and W_e (ny_e*ny_e) when not NULL */
void hvac_set_cost(const hvac_ocp *o, double *yref, double *yref_e, double *W, double *W_e)
{
    for (int k = 0; k < o->N; k++) {
        ocp_nlp_cost_model_set(o->config, o->dims, o->in, k, "yref", yref + k * o->ny);
        if (W) ocp_nlp_cost_model_set(o->config, o->dims, o->in, k, "W", W + k * o->ny * o->ny);
    }
    ocp_nlp_cost_model_set(o->config, o->dims, o->in, o->N, "yref", yref_e);
    if (W_e) ocp_nlp_cost_model_set(o->config, o->dims, o->in, o->N, "W", W_e);
}

/* initial state x0 (nx) and input bounds lbu, ubu (N, nu) */
void hvac_set_bounds(const hvac_ocp *o, double *x0, double *lbu, double *ubu)
{
    ocp_nlp_constraints_model_set(o->config, o->dims, o->in, 0, "lbx", x0);
    ocp_nlp_constraints_model_set(o->config, o->dims, o->in, 0, "ubx", x0);
    for (int k = 0; k < o->N; k++) {
        ocp_nlp_constraints_model_set(o->config, o->dims, o->in, k, "lbu", lbu + k * o->nu);
        ocp_nlp_constraints_model_set(o->config, o->dims, o->in, k, "ubu", ubu + k * o->nu);
    }
}

/* parameters of every stage, (N+1, np) */
void hvac_set_params(const hvac_ocp *o, double *p)
{
    for (int k = 0; k <= o->N; k++) o->update_params(o->capsule, k, p + k * o->np, o->np);
}

/* one phase of the RTI (0 both, 1 preparation, 2 feedback); returns acados' status, qp_iter its QP iterations */
int hvac_solve(const hvac_ocp *o, int phase, int *qp_iter)
{
    ocp_nlp_solver_opts_set(o->config, o->opts, "rti_phase", &phase);
    int status = ocp_nlp_solve(o->solver, o->in, o->out);
    ocp_nlp_get(o->config, o->solver, "qp_iter", qp_iter);
    return status;
}
