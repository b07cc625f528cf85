"""The RTI's QP solved by OSQP's generated C (its embedded code generation), built once per structure.

OSQP writes its workspace for one problem as C (``OSQP.codegen``, embedded mode 2: the matrices' values
can change, their sparsity cannot) together with its own sources. :func:`load` compiles that code with a
small C interface of its own (:data:`GLUE`) into a shared object, caches it on disk
(:func:`.codegen.cache_dir`) named by a hash of what the workspace's behaviour depends on (the sparsity
of P and A, the sizes, OSQP's settings and version, the compiler flags, the processor) and loads it with
``ctypes``. :class:`EmbeddedOsqp` offers the calls the RTI makes (:class:`.rti_osqp._OsqpCore`'s), each
one C call on numpy arrays handed over by address: no scipy matrix, no array copied, no Python object
built per call but the solution array.

The same algorithm as OSQP's Python interface (the same C source of the same version): the matrix
update runs the equilibration and the numeric refactorisation, ``rho`` adapts every
``adaptive_rho_interval`` iterations as set up (the interval is fixed at set-up and written into the
workspace), the warm start and the multipliers kept in the workspace behave alike. The values the
workspace was generated with (the set-up's placeholder linearisation) are replaced before every solve; the
one that carries into later answers is the set-up's gradient (the first matrix update's cost scaling reads
its norm), and :class:`.rti_osqp.RtiOsqpSolver` sets OSQP up with a zero gradient whatever the model. So
the key holds no values, an assumption held by ``tests/test_osqp_embedded.py`` (other model parameters, the
cached solver, the Python interface's commands exactly).

Left out of OSQP's solve (:data:`SOLVE_EDITS`): work whose results no answer reads (the first iteration's
residuals, the objective computed a second time after the loop, the final step size estimate); the matrix update's
Ruiz passes sweep P and A once each (``hq_update_mat_fused``). The workspace and the answers stay OSQP's to the bit.

One thing only the generated code can do: update the matrices without equilibrating again
(``scaling_interval``), the new values scaled with the equilibration in force.

OSQP's embedded code has no timers, so its ``time_limit`` is not available; the time limit is kept
through OSQP's interrupt check instead (:data:`GLUE`: the check is true once the solve has run longer
than the limit, and the status is then OSQP's "run time limit reached").

Each :class:`EmbeddedOsqp` loads its own copy of the shared object (the workspace is the object's
static data), so two solvers never share one, and a fresh copy is a freshly set-up workspace.
"""

from __future__ import annotations

import _ctypes
import ctypes
import hashlib
import os
import platform
import shutil
import tempfile
import weakref
from pathlib import Path

import numpy as np
import osqp

from .codegen import SWITCH_ENV, CodegenReport, _ensure, cache_dir, compile_shared, processor

#: Compiler flags of the generated solver. No fast-math and no contraction into fused multiply-adds:
#: the arithmetic stays that of OSQP's own build, so the answers are the Python interface's.
#: Built for this machine's processor (``-march=native``, the processor in the cache key): 3 % less time per
#: QP than without it, measured (``benchmarks/osqp_generated.py``). ``-fno-math-errno`` (``sqrt`` sets no
#: ``errno``, so the Ruiz passes' square roots vectorise) and ``-funroll-loops`` change no floating-point operation
#: nor its order: the matrix update 0.83x and then 0.94-0.95x, the solve 0.97-1.0x and 0.97-0.98x, the same answers
#: to the bit (docs/architecture.md, 'The step's glue, second pass'); ``-fno-trapping-math`` was slower (1.01-1.02x).
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno", "-funroll-loops", "-fPIC", "-shared",
          "-fvisibility=hidden", "-Wl,-Bsymbolic")
#: Prefix of the generated workspace's names.
PREFIX = "hvac_"
#: OSQP's status values (osqp_api_constants.h) and messages, as its Python interface reports them.
STATUS = {1: "solved", 2: "solved inaccurate", 3: "primal infeasible", 4: "primal infeasible inaccurate",
          5: "dual infeasible", 6: "dual infeasible inaccurate", 7: "maximum iterations reached",
          8: "run time limit reached", 9: "problem non convex", 10: "interrupted", 11: "unsolved"}

#: The C interface compiled with the generated workspace: one function per call of the RTI, and OSQP's
#: interrupt check used as its time limit.
GLUE = r"""
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "osqp.h"
#include "hvac_workspace.h"
#include "algebra_matrix.h"
#include "auxil.h"
#include "kkt.h"
#include "qdldl_interface.h"

#define API __attribute__((visibility("default")))
#define S (&hvac_solver)

static double limit_s = 0.0, deadline_s = 0.0;

static double now_s(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* OSQP's interrupt hooks, used as the time limit of a solve (0: none) */
void osqp_start_interrupt_listener(void) { deadline_s = limit_s > 0.0 ? now_s() + limit_s : 0.0; }
void osqp_end_interrupt_listener(void) {}
int osqp_is_interrupted(void) { return deadline_s > 0.0 && now_s() >= deadline_s; }

API int hq_n(void) { return (int)S->work->data->n; }
API int hq_m(void) { return (int)S->work->data->m; }
API int hq_nnz_p(void) { return (int)OSQPMatrix_get_nz(S->work->data->P); }
API int hq_nnz_a(void) { return (int)OSQPMatrix_get_nz(S->work->data->A); }
API int hq_update_mat(const double* Px, const double* Ax) {
  return (int)osqp_update_data_mat(S, Px, OSQP_NULL, 0, Ax, OSQP_NULL, 0);
}
static void limit_inv_sqrt(OSQPFloat* v, OSQPInt n) {  /* limit_scaling_vector, ew_sqrt, ew_reciprocal */
  OSQPInt i;
  for (i = 0; i < n; i++) {
    OSQPFloat x = v[i] < OSQP_MIN_SCALING ? 1.0 : v[i];
    x = x > OSQP_MAX_SCALING ? OSQP_MAX_SCALING : x;
    v[i] = (OSQPFloat)1.0 / c_sqrt(x);
  }
}

/* the inf-norms of A's columns (into ca) and rows (into ra), after scaling A's values by E (e) and D (d) when
   e is not null: one sweep over A for a pass's scaling and the next pass's norms. A maximum does not depend on the
   order its values come in (none is nan: the maximum of |a| ignores a nan the same way in any order), so these are
   the norms OSQP's separate sweep takes of the same values */
static OSQPFloat *col_a = OSQP_NULL, *row_a = OSQP_NULL;
/* the two norm vectors freed when the private copy is unloaded (dlclose runs the destructors) */
__attribute__((destructor)) static void release_norms(void) { free(col_a); free(row_a); col_a = row_a = OSQP_NULL; }
static void scale_norms_a(OSQPCscMatrix* A, const OSQPFloat* e, const OSQPFloat* d, OSQPFloat* ca, OSQPFloat* ra) {
  OSQPInt j, k;
  for (k = 0; k < A->m; k++) ra[k] = 0.0;
  for (j = 0; j < A->n; j++) {
    OSQPFloat cj = 0.0;
    for (k = A->p[j]; k < A->p[j + 1]; k++) {
      OSQPFloat a;
      if (e) { A->x[k] *= e[A->i[k]]; A->x[k] *= d[j]; }
      a = c_absval(A->x[k]);
      cj = c_max(a, cj);
      ra[A->i[k]] = c_max(a, ra[A->i[k]]);
    }
    ca[j] = cj;
  }
}

/* OSQP's matrix update with its equilibration (osqp_update_data_mat: unscale_data, the new values,
   scale_data, the refactorisation) with the passes over P and A fused: every value and vector entry
   goes through the same operations in the same order as in OSQP's functions, so the results are the
   same to the bit, with one sweep over P and one over A a Ruiz pass instead of five each (the sweep that scales
   A takes the next pass's norms of A: scale_norms_a; the sweep that scales P by D applies the pass before's cost
   scaling c first) */
API int hq_update_mat_fused(const double* Px, const double* Ax) {
  OSQPWorkspace* w = S->work;
  OSQPScaling* sc;
  OSQPCscMatrix *P, *A;
  OSQPInt n, m, nnzP, nnzA, i, j, k, pass;
  OSQPFloat *q, *l, *u, *D, *E, *Dinv, *Einv, *dt, *da, *et;
  OSQPFloat c_temp, norm_q, c_last = 1.0;
  if (!S->settings->scaling) return (int)osqp_update_data_mat(S, Px, OSQP_NULL, 0, Ax, OSQP_NULL, 0);
  sc = w->scaling;
  n = w->data->n; m = w->data->m;
  if (!col_a) col_a = (OSQPFloat*)malloc(sizeof(OSQPFloat) * (size_t)n);  /* before the workspace is touched */
  if (!row_a) row_a = (OSQPFloat*)malloc(sizeof(OSQPFloat) * (size_t)m);
  if (!col_a || !row_a) return -1;
  P = w->data->P->csc;
  A = w->data->A->csc;
  nnzP = P->p[n]; nnzA = A->p[n];
  q = w->data->q->values; l = w->data->l->values; u = w->data->u->values;
  D = sc->D->values; E = sc->E->values; Dinv = sc->Dinv->values; Einv = sc->Einv->values;
  dt = w->D_temp->values; da = w->D_temp_A->values; et = w->E_temp->values;
  for (i = 0; i < n; i++) q[i] *= sc->cinv;          /* unscale_data's vector part */
  for (i = 0; i < n; i++) q[i] *= Dinv[i];
  for (i = 0; i < m; i++) l[i] *= Einv[i];
  for (i = 0; i < m; i++) u[i] *= Einv[i];
  memcpy(P->x, Px, sizeof(OSQPFloat) * (size_t)nnzP);
  memcpy(A->x, Ax, sizeof(OSQPFloat) * (size_t)nnzA);
  sc->c = 1.0;
  for (i = 0; i < n; i++) D[i] = Dinv[i] = 1.0;
  for (i = 0; i < m; i++) E[i] = Einv[i] = 1.0;
  for (j = 0; j < n; j++) {                           /* the first pass's norms of P's columns */
    OSQPFloat cj = 0.0;
    for (k = P->p[j]; k < P->p[j + 1]; k++) cj = c_max(c_absval(P->x[k]), cj);
    dt[j] = cj;
  }
  scale_norms_a(A, OSQP_NULL, OSQP_NULL, col_a, row_a);  /* the first pass's norms of A */
  for (pass = 0; pass < S->settings->scaling; pass++) {
    for (j = 0; j < n; j++) dt[j] = c_max(dt[j], col_a[j]);  /* the columns' norms of P and A */
    memcpy(et, row_a, sizeof(OSQPFloat) * (size_t)m);
    limit_inv_sqrt(dt, n);
    limit_inv_sqrt(et, m);
    scale_norms_a(A, et, dt, col_a, row_a);           /* A <- E A D, the next pass's norms of A */
    for (j = 0; j < n; j++) {                         /* P <- D (c P) D, its columns' norms into da */
      OSQPFloat cj = 0.0;
      for (k = P->p[j]; k < P->p[j + 1]; k++) {
        if (pass > 0) P->x[k] *= c_last;              /* the last pass's P <- c P, as its own sweep did it */
        P->x[k] *= dt[P->i[k]];
        P->x[k] *= dt[j];
        cj = c_max(c_absval(P->x[k]), cj);
      }
      da[j] = cj;
    }
    for (i = 0; i < n; i++) q[i] *= dt[i];
    for (i = 0; i < n; i++) D[i] *= dt[i];
    for (i = 0; i < m; i++) E[i] *= et[i];
    c_temp = 0.0;                                     /* cost normalisation */
    for (i = 0; i < n; i++) c_temp += c_absval(da[i]);
    c_temp = c_temp / n;
    norm_q = 0.0;
    for (i = 0; i < n; i++) if (c_absval(q[i]) > norm_q) norm_q = c_absval(q[i]);
    norm_q = limit_scaling_scalar(norm_q);
    c_temp = c_max(c_temp, norm_q);
    c_temp = limit_scaling_scalar(c_temp);
    c_temp = 1. / c_temp;
    /* P <- c P is left to the next pass's sweep (or the sweep after the passes); the next pass's norms of P's
       columns are those of c P: c is positive and finite (limit_scaling_scalar bounds its reciprocal) and rounding
       is monotone and symmetric, so max_k |fl(c x_k)| = fl(c max_k |x_k|), the same value to the bit */
    for (j = 0; j < n; j++) dt[j] = da[j] * c_temp;
    c_last = c_temp;
    for (i = 0; i < n; i++) q[i] *= c_temp;
    sc->c *= c_temp;
  }
  if (S->settings->scaling > 0)
    for (k = 0; k < nnzP; k++) P->x[k] *= c_last;    /* the last pass's P <- c P */
  sc->cinv = 1. / sc->c;
  for (i = 0; i < n; i++) Dinv[i] = (OSQPFloat)1.0 / D[i];
  for (i = 0; i < m; i++) Einv[i] = (OSQPFloat)1.0 / E[i];
  for (i = 0; i < m; i++) l[i] *= E[i];
  for (i = 0; i < m; i++) u[i] *= E[i];
  k = w->linsys_solver->update_matrices(w->linsys_solver, w->data->P, OSQP_NULL, nnzP,
                                        w->data->A, OSQP_NULL, nnzA);
  reset_info(S->info);
  return (int)k;
}

/* the new values of P and A scaled with the equilibration in force (not computed again), then the
   numeric refactorisation: OSQP's matrix update without its Ruiz passes */
API int hq_update_mat_kept_scaling(const double* Px, const double* Ax) {
  OSQPWorkspace* w = S->work;
  OSQPInt nnzP = OSQPMatrix_get_nz(w->data->P), nnzA = OSQPMatrix_get_nz(w->data->A);
  OSQPInt flag;
  OSQPMatrix_update_values(w->data->P, Px, OSQP_NULL, nnzP);
  OSQPMatrix_update_values(w->data->A, Ax, OSQP_NULL, nnzA);
  if (S->settings->scaling) {
    OSQPMatrix_mult_scalar(w->data->P, w->scaling->c);
    OSQPMatrix_lmult_diag(w->data->P, w->scaling->D);
    OSQPMatrix_rmult_diag(w->data->P, w->scaling->D);
    OSQPMatrix_lmult_diag(w->data->A, w->scaling->E);
    OSQPMatrix_rmult_diag(w->data->A, w->scaling->D);
  }
  flag = w->linsys_solver->update_matrices(w->linsys_solver, w->data->P, OSQP_NULL, nnzP,
                                           w->data->A, OSQP_NULL, nnzA);
  reset_info(S->info);
  return (int)flag;
}
/* OSQP's step size set to rho as osqp_update_rho sets it (the settings, rho_vec and its reciprocals, the KKT
   matrix's rho entries) without its refactorisation: the next matrix update's refactorisation takes it in, so a
   step size reset with a matrix update costs one factorisation, as the update alone does */
API void hq_rho_next_update(double rho) {
  OSQPWorkspace* w = S->work;
  qdldl_solver* s = (qdldl_solver*)w->linsys_solver;
  OSQPInt i;
  S->settings->rho = c_min(c_max(rho, OSQP_RHO_MIN), OSQP_RHO_MAX);
  if (S->settings->rho_is_vec) {
    OSQPVectorf_set_scalar_conditional(w->rho_vec, w->constr_type, OSQP_RHO_MIN, S->settings->rho,
                                       OSQP_RHO_EQ_OVER_RHO_INEQ * S->settings->rho);
    OSQPVectorf_ew_reciprocal(w->rho_inv_vec, w->rho_vec);
  } else {
    w->rho_inv = 1. / S->settings->rho;
  }
  if (s->rho_inv_vec) {
    for (i = 0; i < s->m; i++) s->rho_inv_vec[i] = 1. / w->rho_vec->values[i];
  } else {
    s->rho_inv = 1. / S->settings->rho;
  }
  update_KKT_param2(s->KKT, s->rho_inv_vec, s->rho_inv, s->rhotoKKT, s->m);
}
API int hq_update_vec(const double* q, const double* l, const double* u) {
  return (int)osqp_update_data_vec(S, q, l, u);
}
API int hq_warm_start(const double* x, const double* y) { return (int)osqp_warm_start(S, x, y); }
API int hq_settings(double alpha, int max_iter, int check_termination, double eps_abs, double eps_rel) {
  OSQPSettings s = *S->settings;
  s.alpha = alpha; s.max_iter = max_iter; s.check_termination = check_termination;
  s.eps_abs = eps_abs; s.eps_rel = eps_rel;
  return (int)osqp_update_settings(S, &s);
}
API void hq_time_limit(double seconds) { limit_s = seconds; }
API double hq_rho(void) { return (double)S->settings->rho; }
/* OSQP's step-size adaptation: its estimate checked every interval iterations, taken where it differs from rho by
   more than tolerance times (both fixed at set-up by OSQP's own interface; read at every adaptation check) */
API void hq_rho_adaptation(int interval, double tolerance) {
  S->settings->adaptive_rho_interval = interval;
  S->settings->adaptive_rho_tolerance = tolerance;
}
API int hq_rho_interval(void) { return (int)S->settings->adaptive_rho_interval; }
API double hq_rho_tolerance(void) { return (double)S->settings->adaptive_rho_tolerance; }
/* OSQP's workspace as the next solve finds it, saved into buf and restored from it (split_replays_change): the
   multipliers y (scaled), the scaled P and A, the equilibration, the constraint types, the step size rho (its
   reciprocal, the last KKT error of its adaptation); the primal iterate and q, l, u are what the warm start and
   the vector update write anew. hq_state_size: the doubles of buf. */
static OSQPInt state_parts(OSQPFloat** part, OSQPInt* len) {
  OSQPWorkspace* w = S->work;
  OSQPInt n = w->data->n, m = w->data->m, k = 0;
  part[k] = w->y->values; len[k++] = m;
  part[k] = w->data->P->csc->x; len[k++] = OSQPMatrix_get_nz(w->data->P);
  part[k] = w->data->A->csc->x; len[k++] = OSQPMatrix_get_nz(w->data->A);
  if (S->settings->scaling) {
    part[k] = w->scaling->D->values; len[k++] = n;
    part[k] = w->scaling->Dinv->values; len[k++] = n;
    part[k] = w->scaling->E->values; len[k++] = m;
    part[k] = w->scaling->Einv->values; len[k++] = m;
  }
  return k;
}
#define STATE_SCALARS 5
API int hq_state_size(void) {
  OSQPFloat* part[8]; OSQPInt len[8], k, size = STATE_SCALARS + S->work->data->m, np = state_parts(part, len);
  for (k = 0; k < np; k++) size += len[k];
  return (int)size;
}
API void hq_save_state(double* buf) {
  OSQPWorkspace* w = S->work;
  OSQPFloat* part[8]; OSQPInt len[8], k, i, np = state_parts(part, len), m = w->data->m;
  for (k = 0; k < np; k++) { memcpy(buf, part[k], sizeof(OSQPFloat) * (size_t)len[k]); buf += len[k]; }
  for (i = 0; i < m; i++) buf[i] = (double)w->constr_type->values[i];
  buf += m;
  buf[0] = S->settings->scaling ? w->scaling->c : 1.0;
  buf[1] = S->settings->scaling ? w->scaling->cinv : 1.0;
  buf[2] = S->settings->rho; buf[3] = w->rho_inv; buf[4] = w->last_rel_kkt;
}
/* the saved values back, the step size's vectors and the KKT matrix's entries from them (hq_rho_next_update) and
   the numeric refactorisation of that KKT matrix: the factors of the same values, so the same to the bit */
API int hq_restore_state(const double* buf) {
  OSQPWorkspace* w = S->work;
  OSQPFloat* part[8]; OSQPInt len[8], k, i, np = state_parts(part, len), m = w->data->m;
  for (k = 0; k < np; k++) { memcpy(part[k], buf, sizeof(OSQPFloat) * (size_t)len[k]); buf += len[k]; }
  for (i = 0; i < m; i++) w->constr_type->values[i] = (OSQPInt)buf[i];
  buf += m;
  if (S->settings->scaling) { w->scaling->c = buf[0]; w->scaling->cinv = buf[1]; }
  hq_rho_next_update(buf[2]);
  w->rho_inv = buf[3]; w->last_rel_kkt = buf[4];
  k = w->linsys_solver->update_matrices(w->linsys_solver, w->data->P, OSQP_NULL, len[1],
                                        w->data->A, OSQP_NULL, len[2]);
  reset_info(S->info);
  return (int)k;
}
/* solve; the primal solution into x, [status value, iterations] into info; OSQP's exit flag returned */
API int hq_solve(double* x, long long* info) {
  int flag = (int)osqp_solve(S);
  if (S->info->status_val == OSQP_SIGINT) {  /* the time limit: a status, not an error */
    flag = 0;
    S->info->status_val = OSQP_TIME_LIMIT_REACHED;
    strcpy(S->info->status, "run time limit reached");
  }
  memcpy(x, S->solution->x, sizeof(double) * (size_t)S->work->data->n);
  info[0] = (long long)S->info->status_val;
  info[1] = (long long)S->info->iter;
  return flag;
}
"""

#: Edits of OSQP's generated ``src/osqp_api.c`` (``osqp_solve``), each ``(what, OSQP's text, ours)``: work whose
#: results no answer reads, left out. An edit whose text is not found fails the build (the Python interface then
#: solves, ``load``'s report says why), so another OSQP version is never built half edited. Every value the
#: iterations, the termination, the step size's adaptation and the solution read is computed as before, so the
#: solution, the status and the iterations are OSQP's to the bit (``tests/test_osqp_embedded.py``).
SOLVE_EDITS = (
    # update_info at the first iteration: its residuals, objective and gap are computed again, from the iterate they
    # are read for, at every iteration that reads them (a termination check, a step size adaptation, the end of the
    # loop); only the iteration count it records is read in between (a solve interrupted by the time limit reports
    # it), so only that is kept
    ("the first iteration's residuals",
     "    if(can_check_termination || can_print || can_adapt_rho || iter == 1) {",
     "    if (iter == 1 && !(can_check_termination || can_print || can_adapt_rho)) solver->info->iter = iter;\n"
     "    if(can_check_termination || can_print || can_adapt_rho) {"),
    # the objective and gap after the loop: the last update_info computed them from the same x, y, P x, q, l and u
    # (nothing between writes those), into the same fields, so the call repeats the same values
    ("the objective computed again after the loop",
     "  if (has_solution(solver->info)){\n"
     "    compute_obj_val_dual_gap(solver, work->x, work->y,",
     "  if (0){\n"
     "    compute_obj_val_dual_gap(solver, work->x, work->y,"),
    # the step size OSQP would suggest, for its info only (the adaptation computes its own when it adapts)
    ("the final step size estimate",
     "  solver->info->rho_estimate = compute_rho_estimate(solver);",
     "  /* info->rho_estimate not computed: no answer reads it */"),
)


def edit_solve(source: str) -> str:
    """``osqp_api.c``'s text with :data:`SOLVE_EDITS` made; ``ValueError`` naming the edit whose text is not found
    once."""
    for what, old, new in SOLVE_EDITS:
        if source.count(old) != 1:
            raise ValueError(f"OSQP's osqp_api.c: the text of the edit {what!r} found {source.count(old)} times, "
                             f"expected once (another OSQP version?)")
        source = source.replace(old, new)
    return source


#: OSQP's interrupt hooks as its sources declare them (the header is not among its generated sources).
INTERRUPT_H = """#ifndef INTERRUPT_H
#define INTERRUPT_H
void osqp_start_interrupt_listener(void);
void osqp_end_interrupt_listener(void);
int osqp_is_interrupted(void);
#endif
"""

_DOUBLE = ctypes.c_void_p


def structure_key(wrapper: osqp.OSQP, P_pattern: tuple, A_pattern: tuple) -> str:
    """Hash of what the generated workspace's answers depend on: the sparsity of P and A (``(indices,
    indptr, shape)``), OSQP's settings after set-up and its version, the flags, the glue and the machine."""
    h = hashlib.sha256()
    for indices, indptr, shape in (P_pattern, A_pattern):
        h.update(np.asarray(indices, np.int64).tobytes())
        h.update(np.asarray(indptr, np.int64).tobytes())
        h.update(repr(tuple(shape)).encode())
    st = wrapper.settings
    h.update(repr(sorted((k, getattr(st, k)) for k in dir(st) if not k.startswith("_")
                         and isinstance(getattr(st, k), (int, float, bool, str)))).encode())
    h.update(osqp.__version__.encode())
    h.update(" ".join(CFLAGS).encode())
    h.update(GLUE.encode())
    h.update(repr(SOLVE_EDITS).encode())
    h.update(platform.machine().encode())
    h.update(processor().encode())
    return h.hexdigest()[:20]


def load(wrapper: osqp.OSQP, P_pattern: tuple, A_pattern: tuple, first_pass_iter: int = 0,
         report: CodegenReport | None = None, scaling_interval: int = 1,
         build: bool = True) -> "EmbeddedOsqp | None":
    """The generated solver of the problem ``wrapper`` is set up with (built on first use, then loaded from
    the cache), or None when code generation is off or fails (the reason in ``report["osqp"]``); the
    caller then keeps OSQP's Python interface. ``wrapper`` must have been set up with a zero gradient (the
    RTI's set-up): the set-up's values are not part of the key. ``build`` False: load from the cache only,
    never compile (a reset inside a control step)."""
    report = report if report is not None else CodegenReport()
    if os.environ.get(SWITCH_ENV, "1") == "0":
        report.outcomes["osqp"] = f"interpreted: {SWITCH_ENV}=0"
        return None
    try:
        lib = cache_dir() / "osqp" / f"osqp_{structure_key(wrapper, P_pattern, A_pattern)}.so"
        if not build and not lib.exists():
            report.outcomes["osqp"] = "interpreted: not in the cache (no build inside a control step)"
            return None
        outcome = _ensure(lib, lambda: _build(wrapper, lib), report)
        solver = EmbeddedOsqp(lib, wrapper, first_pass_iter, scaling_interval)
        report.outcomes["osqp"] = outcome
        return solver
    except Exception as exc:  # noqa: BLE001 - no compiler, a codegen OSQP lacks, ...: the Python interface works
        report.outcomes["osqp"] = f"interpreted: {type(exc).__name__}: {str(exc)[:200]}"
        return None


def _build(wrapper: osqp.OSQP, lib: Path) -> None:
    """OSQP's generated workspace and sources with :data:`GLUE`, compiled into ``lib``."""
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        folder = Path(tmp) / "osqp"
        wrapper.codegen(str(folder), parameters="matrices", extension_name=None, force_rewrite=True,
                        prefix=PREFIX, interrupt_enable=True)
        api = folder / "src" / "osqp_api.c"
        api.write_text(edit_solve(api.read_text()))
        (folder / "interrupt.h").write_text(INTERRUPT_H)
        (folder / "hvac_glue.c").write_text(GLUE)
        one = folder / "all.c"  # one translation unit: compile_shared takes one source
        sources = sorted((folder / "src").glob("*.c")) + [folder / f"{PREFIX}workspace.c", folder / "hvac_glue.c"]
        one.write_text("".join(f'#include "{s}"\n' for s in sources))
        includes = tuple(f"-I{folder / d}" for d in ("inc/public", "inc/private", "."))
        compile_shared(one, lib, (*CFLAGS, *includes), ("-lm",), timeout_s=600)


#: OSQP's tolerance in the first pass, relative to its own (:class:`TwoPassSolve`): a QP ends there only
#: when it is that much closer to converged. Measured on the full winter_heating_steps scenario (seed 0):
#: at the tolerance itself the MPC's slowest temperature step took 168 s to the band (81 s with
#: OSQP's settings before the first pass), at half of it 82 s.
FIRST_PASS_EPS_RATIO = 0.5


class TwoPassSolve:
    """The RTI's solve in one pass or two (``first_pass_iter > 0``, :class:`.rti_osqp._OsqpCore`): OSQP's
    settings of both passes from its set-up, switched by :meth:`_apply` (of the subclass) only on a change."""

    #: True where :meth:`_solve_once` returns a new array of its own for each solve (nothing else holds it, so the
    #: caller may keep it without a copy); False where it may be a view of the solver's memory.
    fresh_solution = False

    def _passes(self, st, first_pass_iter: int) -> None:
        self.first_pass_iter = int(first_pass_iter)
        # the continuation's cap leaves room for the pass's iterations: ``max_iter`` bounds the whole QP
        full_cap = max(st.max_iter - self.first_pass_iter, 1) if self.first_pass_iter > 0 else st.max_iter
        self._full = dict(alpha=st.alpha, max_iter=full_cap, check_termination=st.check_termination,
                          eps_abs=st.eps_abs, eps_rel=st.eps_rel)
        self._first = dict(alpha=1.0, max_iter=self.first_pass_iter, check_termination=self.first_pass_iter,
                           eps_abs=st.eps_abs * FIRST_PASS_EPS_RATIO, eps_rel=st.eps_rel * FIRST_PASS_EPS_RATIO)
        self._mode = "full"

    def _apply(self, values: dict) -> None:
        raise NotImplementedError

    def _solve_once(self) -> tuple[int, str, int, np.ndarray]:
        raise NotImplementedError

    def _use(self, mode: str) -> None:
        """Switch OSQP's iteration settings to the first pass or the full solve (a call only on a change)."""
        if mode != self._mode:
            self._apply(self._first if mode == "first" else self._full)
            self._mode = mode

    def solve_capped(self, max_iter: int) -> tuple[int, str, int, np.ndarray]:
        """One pass of the full solve's settings with at most ``max_iter`` (>= 1) iterations (no first pass), as
        :meth:`solve` returns; the full solve's settings are in force afterwards."""
        if int(max_iter) < 1:
            raise ValueError(f"{type(self).__name__}.solve_capped: max_iter = {max_iter!r}, allowed: an integer >= 1")
        self._apply(dict(self._full, max_iter=int(max_iter)))
        self._mode = "capped"
        try:
            return self._solve_once()
        finally:
            self._use("full")

    def solve(self) -> tuple[int, str, int, np.ndarray]:
        """Solve; returns OSQP's status value and text, the iterations (both passes) and the primal solution."""
        iterations = 0
        if self.first_pass_iter > 0:
            self._use("first")
            status_val, status, n, x = self._solve_once()
            if status_val == 1:  # solved within the pass
                return status_val, status, n, x
            iterations = n
            self._use("full")
        status_val, status, n, x = self._solve_once()
        return status_val, status, iterations + n, x


class EmbeddedOsqp(TwoPassSolve):
    """One generated OSQP workspace, called as the RTI calls OSQP (:class:`.rti_osqp._OsqpCore`'s methods).

    ``first_pass_iter > 0``: each solve first runs that many iterations without over-relaxation, as
    :class:`.rti_osqp._OsqpCore` does (the settings of both passes taken from ``wrapper``).
    ``scaling_interval``: OSQP's equilibration on every this many matrix updates (1: on each, as OSQP
    does); the others keep the last one's, which saves its Ruiz passes and changes the ADMM iterates."""

    fresh_solution = True  # _solve_once: a new array per solve

    def __init__(self, lib: Path, wrapper: osqp.OSQP, first_pass_iter: int = 0, scaling_interval: int = 1):
        if int(scaling_interval) < 1:
            raise ValueError(f"EmbeddedOsqp: scaling_interval = {scaling_interval!r}, allowed: an integer >= 1")
        self.scaling_interval = int(scaling_interval)
        self._updates = 0
        self._lib = _private_copy(lib)
        weakref.finalize(self, _close, self._lib._handle).atexit = False  # not while exit handlers may still solve
        f = self._lib
        for name, args, res in (("hq_update_mat", [_DOUBLE] * 2, ctypes.c_int),
                                ("hq_update_mat_kept_scaling", [_DOUBLE] * 2, ctypes.c_int),
                                ("hq_update_mat_fused", [_DOUBLE] * 2, ctypes.c_int),
                                ("hq_update_vec", [_DOUBLE] * 3, ctypes.c_int),
                                ("hq_warm_start", [_DOUBLE] * 2, ctypes.c_int),
                                ("hq_settings", [ctypes.c_double, ctypes.c_int, ctypes.c_int, ctypes.c_double,
                                                 ctypes.c_double], ctypes.c_int),
                                ("hq_time_limit", [ctypes.c_double], None), ("hq_rho", [], ctypes.c_double),
                                ("hq_rho_next_update", [ctypes.c_double], None),
                                ("hq_rho_adaptation", [ctypes.c_int, ctypes.c_double], None),
                                ("hq_rho_interval", [], ctypes.c_int), ("hq_rho_tolerance", [], ctypes.c_double),
                                ("hq_solve", [_DOUBLE, _DOUBLE], ctypes.c_int),
                                ("hq_state_size", [], ctypes.c_int), ("hq_save_state", [_DOUBLE], None),
                                ("hq_restore_state", [_DOUBLE], ctypes.c_int),
                                ("hq_n", [], ctypes.c_int), ("hq_m", [], ctypes.c_int),
                                ("hq_nnz_p", [], ctypes.c_int), ("hq_nnz_a", [], ctypes.c_int)):
            getattr(f, name).argtypes = args
            getattr(f, name).restype = res
        self.n, self.m = int(f.hq_n()), int(f.hq_m())
        self._nnz_p, self._nnz_a = int(f.hq_nnz_p()), int(f.hq_nnz_a())
        self._state_size = int(f.hq_state_size())
        self._info = np.zeros(2, np.int64)
        self._info_p = self._info.ctypes.data
        self._bounds: tuple | None = None  # the bound arrays last handed over and their addresses (update_vectors)
        self._held: list[tuple | None] = [None, None, None]  # P's and A's values and q last handed over, addresses
        self._passes(wrapper.settings, first_pass_iter)

    @staticmethod
    def _check(flag: int, what: str) -> None:
        if flag != 0:
            raise RuntimeError(f"generated OSQP: {what} failed (exit flag {flag})")

    @staticmethod
    def _p(a: np.ndarray, size: int) -> int:
        """Address of ``a``'s data; ``a`` must be a contiguous float64 array of ``size`` values (checked:
        a wrong array would be read past its end by C)."""
        if a.dtype != np.float64 or a.size != size or not a.flags.c_contiguous:
            raise ValueError(f"generated OSQP: expected a contiguous float64 array of {size} values, "
                             f"got {a.dtype} of shape {a.shape}")
        return data_address(a)

    def update_matrices(self, Px: np.ndarray, Ax: np.ndarray) -> None:
        """The values of P (upper triangle) and A in OSQP's CSC order, then the numeric refactorisation.
        OSQP's equilibration runs again on every ``scaling_interval``-th update (the first included); the
        updates between scale the new values with the equilibration in force."""
        Px_p, Ax_p = self._held_address(0, Px, self._nnz_p), self._held_address(1, Ax, self._nnz_a)
        if self._updates % self.scaling_interval == 0:
            self._check(self._lib.hq_update_mat_fused(Px_p, Ax_p), "matrix update")
        else:
            self._check(self._lib.hq_update_mat_kept_scaling(Px_p, Ax_p), "matrix update")
        self._updates += 1

    def update_vectors(self, q: np.ndarray, l: np.ndarray, u: np.ndarray) -> None:
        """``l``, ``u`` already within OSQP's infinity."""
        n, m = self.n, self.m
        if self._bounds is None or self._bounds[0] is not l or self._bounds[1] is not u:
            # the caller's bound arrays are the same from QP to QP: their addresses are taken (and checked) once, and
            # the arrays held, so neither can be freed or moved meanwhile
            self._bounds = (l, u, self._p(l, m), self._p(u, m))
        # its exit flag (e.g. a lower bound above an upper one) is not raised, as OSQP's Python interface does not:
        # the solve then reports the problem infeasible, which the RTI treats as a failed QP
        self._lib.hq_update_vec(self._held_address(2, q, n), self._bounds[2], self._bounds[3])

    def _held_address(self, slot: int, a: np.ndarray, size: int) -> int:
        """:meth:`_p` of ``a``, taken (and checked) once while the same array comes back in ``slot`` (0: P's values,
        1: A's, 2: the gradient) and the array held meanwhile, so it cannot be freed or moved: the step hands over the
        buffers of its generated calls (``BufferedFunction.views``), the same arrays every step."""
        held = self._held[slot]
        if held is None or held[0] is not a:
            held = self._held[slot] = (a, self._p(a, size))
        return held[1]

    def warm_start(self, x: np.ndarray, y: np.ndarray | None = None) -> None:
        """Primal warm start; the multipliers stay those of the last solve unless ``y`` is given."""
        self._check(self._lib.hq_warm_start(self._p(x, self.n), None if y is None else self._p(y, self.m)),
                    "warm start")

    def set_time_limit(self, seconds: float) -> None:
        """Time limit of each solve from now on (s; 0: none)."""
        self._lib.hq_time_limit(float(seconds))

    @property
    def rho(self) -> float:
        """OSQP's step size now (it adapts during solves and is kept from one QP to the next)."""
        return float(self._lib.hq_rho())

    def rho_next_update(self, rho: float) -> None:
        """OSQP's step size set to ``rho`` from the next matrix update on (:meth:`update_matrices`, whose
        refactorisation takes it in: no factorisation of its own; OSQP's ``update_rho`` and then the update give the
        same workspace)."""
        self._lib.hq_rho_next_update(float(rho))

    @property
    def rho_adaptation(self) -> tuple[int, float]:
        """OSQP's step-size adaptation now: its interval (iterations) and tolerance (a factor)."""
        return int(self._lib.hq_rho_interval()), float(self._lib.hq_rho_tolerance())

    def set_rho_adaptation(self, interval: int, tolerance: float) -> bool:
        """OSQP's step size adapted every ``interval`` (>= 1) iterations where its estimate differs by more than
        ``tolerance`` (> 1) times, from the next solve on (OSQP's own interface fixes both at set-up; the solve reads
        them at every check). Returns True (done)."""
        if int(interval) < 1 or not float(tolerance) > 1.0:
            raise ValueError(f"EmbeddedOsqp.set_rho_adaptation: interval = {interval!r}, tolerance = {tolerance!r}; "
                             "allowed: an integer >= 1 and a number > 1")
        self._lib.hq_rho_adaptation(int(interval), float(tolerance))
        return True

    def save_state(self) -> dict:
        """OSQP's workspace as the next solve finds it (the multipliers, the scaled matrices and their equilibration,
        the constraint types, the step size; the matrix updates counted for ``scaling_interval``), for
        :meth:`restore_state`. The primal iterate and the vectors are not in it: the warm start and the vector update
        that precede every solve write them anew."""
        buf = np.empty(self._state_size)
        self._lib.hq_save_state(buf.ctypes.data)
        return {"buf": buf, "updates": self._updates}

    def restore_state(self, state: dict) -> None:
        """The workspace of :meth:`save_state` back, its KKT matrix factorised again (one numeric factorisation):
        a solve after the same vector update and warm start gives the same iterates, to the bit, as it would have
        given right after the save."""
        buf = state["buf"]
        self._check(self._lib.hq_restore_state(self._p(buf, self._state_size)), "state restore")
        self._updates = state["updates"]

    def _apply(self, values: dict) -> None:
        self._check(self._lib.hq_settings(values["alpha"], values["max_iter"], values["check_termination"],
                                          values["eps_abs"], values["eps_rel"]), "settings")

    def _solve_once(self) -> tuple[int, str, int, np.ndarray]:
        x = np.empty(self.n)
        self._check(self._lib.hq_solve(data_address(x), self._info_p), "solve")
        status_val = int(self._info[0])
        return status_val, STATUS.get(status_val, "unknown"), int(self._info[1]), x


def data_address(a: np.ndarray) -> int:
    """The address of a contiguous array's data, through ctypes' view of its buffer (a third of
    ``ndarray.ctypes.data``'s time: 0.3 against 0.9 us of thread CPU, ``benchmarks/quiet_profile.py``; a step hands
    OSQP five or six arrays); ``ndarray.ctypes.data`` where the buffer is read-only (ctypes views only writable ones)."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):
        return a.ctypes.data


def _close(handle: int) -> None:
    """Unload a private copy (its workspace) once its solver is gone."""
    _ctypes.dlclose(handle)


def _private_copy(lib: Path) -> ctypes.CDLL:
    """``lib`` loaded from a copy of its own (the workspace is the object's static data: a copy per
    solver), the copy's file removed once loaded."""
    fd, name = tempfile.mkstemp(suffix=".so", dir=lib.parent)
    os.close(fd)
    try:
        shutil.copyfile(lib, name)
        return ctypes.CDLL(name, mode=os.RTLD_LOCAL)
    finally:
        os.unlink(name)
