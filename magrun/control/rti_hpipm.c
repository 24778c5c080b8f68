/* The RTI's per-tick work in C: linearise every stage, fill HPIPM's stage-wise QP, solve.
 *
 * Compiled by magrun/control/rti_kernel.py into one shared library together with the
 * CasADi-generated stage functions, which define before this file is included:
 *
 *   rti_stage(s, v, par)   -> s_next, A = ds_next/ds, B = ds_next/dv, r, Js = dr/ds, Jv = dr/dv,
 *                             g, Gs = dg/ds, Gv = dg/dv
 *   rti_terminal(s, par)   -> rN, JN = drN/ds, gN, GN = dgN/ds
 *   rti_heading(X, u)      -> the heading-stable field's residual (one row, or none)
 *   rti_step(X, u)         -> X_next, one step of the model (the planner's prediction)
 *
 * all outputs dense and column-major, and the dimensions RTI_N (horizon), RTI_NS (stage
 * state s = (X, u_prev)), RTI_NU (currents), RTI_NR / RTI_NRT (stage / terminal residual
 * rows), RTI_NG / RTI_NGT (stage / terminal soft-constraint rows), RTI_NGH (the first of the
 * stage's soft rows that stage 0 keeps: the heading's, the only ones that depend on v_0),
 * RTI_NP (stage parameters), RTI_NB (bounded state entries), RTI_HEADING (0 or 1).
 *
 * The QP is in steps from the iterate (S = s_1 … s_N, V = v_0 … v_{N-1}), with the
 * Gauss-Newton cost of the stacked residuals, 1/2 |r + Js ds + Jv dv|^2 per stage:
 *
 *   Q = Js'Js, S = Jv'Js (nu x nx), R = Jv'Jv, q = Js'r, r = Jv'r, (+ reg on the diagonals)
 *
 * reg is RTI_REG plus the step damping mu (rti_set_damping; 0 unless set): mu/2 |step|^2 in
 * the QP, a Levenberg-Marquardt proximal term on every state and control step. It leaves
 * the iteration's fixed points where they are and shortens each step.
 *   ds_{k+1} = A_k ds_k + B_k dv_k + (f(s_k, v_k) - s_{k+1})
 *
 * and the soft constraints g(s, v) >= 0 (the weighted gaps of the heading-stable field and
 * the corridor) linearised, each with a slack sl >= 0 that costs sl^2 (1/2 sl^2 in this
 * QP, whose cost is half the problem's):
 *
 *   g + Gs ds + Gv dv + sl >= 0           (HPIPM: lg = -g, C = Gs, D = Gv, Zl = 1, zl = 0)
 *
 * the same penalty as a residual min(0, g) in the cost, whose Gauss-Newton model is blind to
 * a constraint inactive at the iterate: one step then plans straight through it, the next
 * back out, and a real-time iteration (one step a tick) alternates between the two.
 *
 * Stage 0 has no state in the QP: its start s_0 is given. The stage is linearised at a point
 * s_lin (prepare) and the measured s_0 enters when it is known (feedback), exactly for the
 * linear model: b_0 = gap_0 + A_0 (s_0 - s_lin), r_0 = Jv_0'(r_0 + Js_0 (s_0 - s_lin)),
 * lg_0 = -(g_0 + Gs_0 (s_0 - s_lin)).
 * That is the real-time iteration's preparation / feedback split; with s_lin = s_0 it is the
 * plain iteration.
 *
 * Why hand-written: CasADi's HPIPM interface takes one global sparse QP, splits it back into
 * stages and allocates HPIPM's structures on every call; here the stages are filled
 * directly and the structures live as long as the controller. HPIPM does the solving.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "hpipm_common.h"
#include "hpipm_d_ocp_qp.h"
#include "hpipm_d_ocp_qp_dim.h"
#include "hpipm_d_ocp_qp_ipm.h"
#include "hpipm_d_ocp_qp_sol.h"

#define RTI_REG 1e-9 /* keeps H positive definite along the unweighted velocities */
#define RTI_NX (RTI_NS - RTI_NU) /* the state in a stage s = (X, u_prev) */
/* array sizes that may be zero */
#define RTI_NG1 (RTI_NG > 0 ? RTI_NG : 1)
#define RTI_NGT1 (RTI_NGT > 0 ? RTI_NGT : 1)
#define RTI_NGMAX (RTI_NG1 > RTI_NGT1 ? RTI_NG1 : RTI_NGT1)

typedef struct {
    double S[RTI_N * RTI_NS]; /* s_1 … s_N, one after another */
    double V[RTI_N * RTI_NU]; /* v_0 … v_{N-1} */
    double s_lin[RTI_NS], par0[RTI_NP];
    /* stage 0's linearisation, for the feedback */
    double A0[RTI_NS * RTI_NS], gap0[RTI_NS], r0[RTI_NR], Js0[RTI_NR * RTI_NS],
        Jv0[RTI_NR * RTI_NU], g0[RTI_NG1], Gs0[RTI_NG1 * RTI_NS];
    /* bounds */
    double du_max[RTI_NU], s_lb[RTI_NB], s_ub[RTI_NB];
    int idxbx[RTI_NB], idxbu[RTI_NU];
    /* soft constraints: each general row's slack index, its costs, a zero mask */
    int idxs[RTI_NGMAX];
    double Zs[RTI_NGMAX], zs[RTI_NGMAX], off[RTI_NGMAX];
    /* HPIPM */
    int nx[RTI_N + 1], nu[RTI_N + 1], nbx[RTI_N + 1], nbu[RTI_N + 1], ng[RTI_N + 1],
        nsoft[RTI_N + 1];
    struct d_ocp_qp_dim dim;
    struct d_ocp_qp qp;
    struct d_ocp_qp_sol sol;
    struct d_ocp_qp_ipm_arg arg[2]; /* fast (SPEED_ABS), robust (ROBUST) */
    struct d_ocp_qp_ipm_ws ws[2];
    void *memory[6];
    int retries; /* QPs the fast mode failed and the robust one solved */
    double reg;  /* RTI_REG + the step damping */
    /* CasADi work */
    const double **arg_ptr;
    double **res_ptr;
    casadi_int *iw;
    double *w;
    /* scratch */
    double sn[RTI_NS], A[RTI_NS * RTI_NS], B[RTI_NS * RTI_NU], r[RTI_NR], Js[RTI_NR * RTI_NS],
        Jv[RTI_NR * RTI_NU], rN[RTI_NRT], JN[RTI_NRT * RTI_NS], g[RTI_NG1],
        Gs[RTI_NG1 * RTI_NS], Gv[RTI_NG1 * RTI_NU], gN[RTI_NGT1], GN[RTI_NGT1 * RTI_NS],
        lg[RTI_NGMAX], D[RTI_NG1 * RTI_NU];
    double Q[RTI_NS * RTI_NS], Sc[RTI_NU * RTI_NS], R[RTI_NU * RTI_NU], q[RTI_NS], rv[RTI_NU],
        b[RTI_NS], lb[RTI_NS], ub[RTI_NS], lbu[RTI_NU], ubu[RTI_NU], step[RTI_NS];
} rti_mem;

/* out[i + j*n] = sum_l X[l + i*m] Y[l + j*m]  (X'Y; X m x n, Y m x p, column-major) */
static void tmul(int m, int n, int p, const double *X, const double *Y, double *out) {
    for (int j = 0; j < p; ++j)
        for (int i = 0; i < n; ++i) {
            double acc = 0.0;
            const double *x = X + i * m, *y = Y + j * m;
            for (int l = 0; l < m; ++l) acc += x[l] * y[l];
            out[i + j * n] = acc;
        }
}

static void add_reg(int n, double *H, double reg) {
    for (int i = 0; i < n; ++i) H[i + i * n] += reg;
}

static int all_finite(int n, const double *x) {
    for (int i = 0; i < n; ++i)
        if (!isfinite(x[i])) return 0;
    return 1;
}

static void set_arg(struct d_ocp_qp_ipm_arg *arg, enum hpipm_mode mode, const double *tol,
                    int iter_max) {
    double t;
    d_ocp_qp_ipm_arg_set_default(mode, arg);
    d_ocp_qp_ipm_arg_set_iter_max(&iter_max, arg);
    t = tol[0];
    d_ocp_qp_ipm_arg_set_tol_stat(&t, arg);
    t = tol[1];
    d_ocp_qp_ipm_arg_set_tol_eq(&t, arg);
    t = tol[2];
    d_ocp_qp_ipm_arg_set_tol_ineq(&t, arg);
    t = tol[3];
    d_ocp_qp_ipm_arg_set_tol_comp(&t, arg);
}

static void grow(casadi_int *have, casadi_int want) {
    if (want > *have) *have = want;
}

void rti_free(void *handle) {
    rti_mem *m = handle;
    if (!m) return;
    for (int i = 0; i < 6; ++i) free(m->memory[i]);
    free(m->arg_ptr);
    free(m->res_ptr);
    free(m->iw);
    free(m->w);
    free(m);
}

/* du_max (nu): the slew bound on v; idxbx, s_lb, s_ub (nb): the bounded entries of a stage
 * state and their bounds; tol: HPIPM's tolerances (stationarity, equality, inequality,
 * complementarity) and the fast mode's initial barrier parameter mu0; iter_max: its
 * iteration limit. NULL when out of memory. */
void *rti_create(const double *du_max, const int *idxbx, const double *s_lb, const double *s_ub,
                 const double *tol, int iter_max) {
    rti_mem *m = calloc(1, sizeof(rti_mem));
    if (!m) return NULL;
    m->reg = RTI_REG;
    memcpy(m->du_max, du_max, sizeof(m->du_max));
    memcpy(m->idxbx, idxbx, sizeof(m->idxbx));
    memcpy(m->s_lb, s_lb, sizeof(m->s_lb));
    memcpy(m->s_ub, s_ub, sizeof(m->s_ub));
    for (int i = 0; i < RTI_NU; ++i) m->idxbu[i] = i;
    for (int k = 0; k <= RTI_N; ++k) {
        m->nx[k] = k == 0 ? 0 : RTI_NS;
        m->nu[k] = k == RTI_N ? 0 : RTI_NU;
        m->nbx[k] = k == 0 ? 0 : RTI_NB;
        m->nbu[k] = m->nu[k];
        m->ng[k] = k == 0 ? RTI_NGH : k == RTI_N ? RTI_NGT : RTI_NG;
        m->nsoft[k] = m->ng[k];
    }
    for (int i = 0; i < RTI_NGMAX; ++i) m->Zs[i] = 1.0, m->zs[i] = 0.0, m->off[i] = 0.0;
    int ok = 1;
    ok &= (m->memory[0] = malloc(d_ocp_qp_dim_memsize(RTI_N))) != NULL;
    if (!ok) goto fail;
    d_ocp_qp_dim_create(RTI_N, &m->dim, m->memory[0]);
    d_ocp_qp_dim_set_all(m->nx, m->nu, m->nbx, m->nbu, m->ng, m->nsoft, &m->dim);
    ok &= (m->memory[1] = malloc(d_ocp_qp_memsize(&m->dim))) != NULL;
    ok &= (m->memory[2] = malloc(d_ocp_qp_sol_memsize(&m->dim))) != NULL;
    if (!ok) goto fail;
    d_ocp_qp_create(&m->dim, &m->qp, m->memory[1]);
    d_ocp_qp_sol_create(&m->dim, &m->sol, m->memory[2]);
    enum hpipm_mode modes[2] = {SPEED_ABS, ROBUST};
    for (int i = 0; i < 2; ++i) {
        if (!(m->memory[3 + i] = malloc(d_ocp_qp_ipm_arg_memsize(&m->dim)))) goto fail;
        d_ocp_qp_ipm_arg_create(&m->dim, &m->arg[i], m->memory[3 + i]);
        set_arg(&m->arg[i], modes[i], tol, iter_max);
        if (i == 0) d_ocp_qp_ipm_arg_set_mu0((double *)&tol[4], &m->arg[0]);
    }
    /* one workspace block for both modes, used one at a time */
    hpipm_size_t ws0 = d_ocp_qp_ipm_ws_memsize(&m->dim, &m->arg[0]);
    hpipm_size_t ws1 = d_ocp_qp_ipm_ws_memsize(&m->dim, &m->arg[1]);
    hpipm_size_t pad = 64;
    if (!(m->memory[5] = malloc(ws0 + ws1 + pad))) goto fail;
    d_ocp_qp_ipm_ws_create(&m->dim, &m->arg[0], &m->ws[0], m->memory[5]);
    d_ocp_qp_ipm_ws_create(&m->dim, &m->arg[1], &m->ws[1],
                           (char *)m->memory[5] + (ws0 + pad - 1) / pad * pad);
    for (int k = 0; k <= RTI_N; ++k) {
        if (k < RTI_N) d_ocp_qp_set_idxbu(k, m->idxbu, &m->qp);
        if (k > 0) d_ocp_qp_set_idxbx(k, m->idxbx, &m->qp);
        if (m->ng[k] == 0) continue;
        /* the general rows come after the bounds; each row its own slack, which costs
         * 1/2 Zl sl^2 = 1/2 sl^2 (the QP's cost is half the problem's); only the lower side:
         * the upper one is masked off */
        int nb = m->nbu[k] + m->nbx[k];
        for (int i = 0; i < m->ng[k]; ++i) m->idxs[i] = nb + i;
        d_ocp_qp_set_idxs(k, m->idxs, &m->qp);
        d_ocp_qp_set_Zl(k, m->Zs, &m->qp);
        d_ocp_qp_set_Zu(k, m->Zs, &m->qp);
        d_ocp_qp_set_zl(k, m->zs, &m->qp);
        d_ocp_qp_set_zu(k, m->zs, &m->qp);
        d_ocp_qp_set_lls(k, m->off, &m->qp);
        d_ocp_qp_set_lus(k, m->off, &m->qp);
        d_ocp_qp_set_ug(k, m->off, &m->qp);
        d_ocp_qp_set_ug_mask(k, m->off, &m->qp);
    }
    /* CasADi's work vectors: the largest of the three functions' */
    casadi_int n_arg = 0, n_res = 0, n_iw = 0, n_w = 0, a, r, i, w;
    rti_stage_work(&a, &r, &i, &w);
    grow(&n_arg, a), grow(&n_res, r), grow(&n_iw, i), grow(&n_w, w);
    rti_terminal_work(&a, &r, &i, &w);
    grow(&n_arg, a), grow(&n_res, r), grow(&n_iw, i), grow(&n_w, w);
    rti_heading_work(&a, &r, &i, &w);
    grow(&n_arg, a), grow(&n_res, r), grow(&n_iw, i), grow(&n_w, w);
    rti_step_work(&a, &r, &i, &w);
    grow(&n_arg, a), grow(&n_res, r), grow(&n_iw, i), grow(&n_w, w);
    m->arg_ptr = calloc(n_arg + 1, sizeof(double *));
    m->res_ptr = calloc(n_res + 1, sizeof(double *));
    m->iw = calloc(n_iw + 1, sizeof(casadi_int));
    m->w = calloc(n_w + 1, sizeof(double));
    if (!m->arg_ptr || !m->res_ptr || !m->iw || !m->w) goto fail;
    return m;
fail:
    rti_free(m);
    return NULL;
}

/* the iterate in and out: S (N x ns, stage after stage), V (N x nu) */
void rti_set_iterate(void *handle, const double *S, const double *V) {
    rti_mem *m = handle;
    memcpy(m->S, S, sizeof(m->S));
    memcpy(m->V, V, sizeof(m->V));
}

void rti_get_iterate(void *handle, double *S, double *V) {
    rti_mem *m = handle;
    memcpy(S, m->S, sizeof(m->S));
    memcpy(V, m->V, sizeof(m->V));
}

/* the plan moved one stage on: the last state repeated, the last step zero */
void rti_shift(void *handle) {
    rti_mem *m = handle;
    memmove(m->S, m->S + RTI_NS, sizeof(double) * (RTI_N - 1) * RTI_NS);
    memmove(m->V, m->V + RTI_NU, sizeof(double) * (RTI_N - 1) * RTI_NU);
    memset(m->V + (RTI_N - 1) * RTI_NU, 0, sizeof(double) * RTI_NU);
}

/* stage k's state bounds, as bounds on the step from the iterate's state s */
static void set_state_bounds(rti_mem *m, int k, const double *s) {
    for (int i = 0; i < RTI_NB; ++i) {
        double x = s[m->idxbx[i]];
        m->lb[i] = m->s_lb[i] - x;
        m->ub[i] = m->s_ub[i] - x;
    }
    d_ocp_qp_set_lbx(k, m->lb, &m->qp);
    d_ocp_qp_set_ubx(k, m->ub, &m->qp);
}

static void eval_stage(rti_mem *m, const double *s, const double *v, const double *par) {
    m->arg_ptr[0] = s, m->arg_ptr[1] = v, m->arg_ptr[2] = par;
    m->res_ptr[0] = m->sn, m->res_ptr[1] = m->A, m->res_ptr[2] = m->B;
    m->res_ptr[3] = m->r, m->res_ptr[4] = m->Js, m->res_ptr[5] = m->Jv;
    m->res_ptr[6] = m->g, m->res_ptr[7] = m->Gs, m->res_ptr[8] = m->Gv;
    rti_stage(m->arg_ptr, m->res_ptr, m->iw, m->w, 0);
}

/* Linearise every stage around the iterate, stage 0 at s_lin; par: the (NP, N+1) stage
 * parameters, column-major. 0, or -1 when a linearisation is not finite. */
int rti_prepare(void *handle, const double *par, const double *s_lin) {
    rti_mem *m = handle;
    memcpy(m->s_lin, s_lin, sizeof(m->s_lin));
    memcpy(m->par0, par, sizeof(m->par0));
    for (int k = 0; k < RTI_N; ++k) {
        const double *s = k == 0 ? s_lin : m->S + (k - 1) * RTI_NS;
        const double *v = m->V + k * RTI_NU;
        eval_stage(m, s, v, par + k * RTI_NP);
        for (int i = 0; i < RTI_NS; ++i) m->b[i] = m->sn[i] - m->S[k * RTI_NS + i];
        if (!all_finite(RTI_NS, m->b) || !all_finite(RTI_NR, m->r) ||
            !all_finite(RTI_NG, m->g))
            return -1;
        tmul(RTI_NR, RTI_NU, RTI_NU, m->Jv, m->Jv, m->R);
        add_reg(RTI_NU, m->R, m->reg);
        d_ocp_qp_set_R(k, m->R, &m->qp);
        d_ocp_qp_set_B(k, m->B, &m->qp);
        if (k == 0) {
            memcpy(m->A0, m->A, sizeof(m->A0));
            memcpy(m->gap0, m->b, sizeof(m->gap0));
            memcpy(m->r0, m->r, sizeof(m->r0));
            memcpy(m->Js0, m->Js, sizeof(m->Js0));
            memcpy(m->Jv0, m->Jv, sizeof(m->Jv0));
            memcpy(m->g0, m->g, sizeof(m->g0));
            memcpy(m->Gs0, m->Gs, sizeof(m->Gs0));
            if (RTI_NGH > 0) { /* the heading's rows of D (column-major, NG rows) */
                for (int j = 0; j < RTI_NU; ++j)
                    for (int i = 0; i < RTI_NGH; ++i) m->D[i + j * RTI_NGH] = m->Gv[i + j * RTI_NG];
                d_ocp_qp_set_D(0, m->D, &m->qp);
            }
        } else {
            tmul(RTI_NR, RTI_NU, 1, m->Jv, m->r, m->rv);
            tmul(RTI_NR, RTI_NS, RTI_NS, m->Js, m->Js, m->Q);
            add_reg(RTI_NS, m->Q, m->reg);
            tmul(RTI_NR, RTI_NU, RTI_NS, m->Jv, m->Js, m->Sc);
            tmul(RTI_NR, RTI_NS, 1, m->Js, m->r, m->q);
            d_ocp_qp_set_A(k, m->A, &m->qp);
            d_ocp_qp_set_b(k, m->b, &m->qp);
            d_ocp_qp_set_Q(k, m->Q, &m->qp);
            d_ocp_qp_set_S(k, m->Sc, &m->qp);
            d_ocp_qp_set_q(k, m->q, &m->qp);
            d_ocp_qp_set_r(k, m->rv, &m->qp);
            set_state_bounds(m, k, s);
            if (RTI_NG > 0) {
                for (int i = 0; i < RTI_NG; ++i) m->lg[i] = -m->g[i];
                d_ocp_qp_set_C(k, m->Gs, &m->qp);
                d_ocp_qp_set_D(k, m->Gv, &m->qp);
                d_ocp_qp_set_lg(k, m->lg, &m->qp);
            }
        }
        for (int i = 0; i < RTI_NU; ++i) {
            m->lbu[i] = -m->du_max[i] - v[i];
            m->ubu[i] = m->du_max[i] - v[i];
        }
        d_ocp_qp_set_lbu(k, m->lbu, &m->qp);
        d_ocp_qp_set_ubu(k, m->ubu, &m->qp);
    }
    const double *sN = m->S + (RTI_N - 1) * RTI_NS;
    m->arg_ptr[0] = sN, m->arg_ptr[1] = par + RTI_N * RTI_NP;
    m->res_ptr[0] = m->rN, m->res_ptr[1] = m->JN, m->res_ptr[2] = m->gN, m->res_ptr[3] = m->GN;
    rti_terminal(m->arg_ptr, m->res_ptr, m->iw, m->w, 0);
    if (!all_finite(RTI_NRT, m->rN) || !all_finite(RTI_NGT, m->gN)) return -1;
    tmul(RTI_NRT, RTI_NS, RTI_NS, m->JN, m->JN, m->Q);
    add_reg(RTI_NS, m->Q, m->reg);
    tmul(RTI_NRT, RTI_NS, 1, m->JN, m->rN, m->q);
    d_ocp_qp_set_Q(RTI_N, m->Q, &m->qp);
    d_ocp_qp_set_q(RTI_N, m->q, &m->qp);
    set_state_bounds(m, RTI_N, sN);
    if (RTI_NGT > 0) {
        for (int i = 0; i < RTI_NGT; ++i) m->lg[i] = -m->gN[i];
        d_ocp_qp_set_C(RTI_N, m->GN, &m->qp);
        d_ocp_qp_set_lg(RTI_N, m->lg, &m->qp);
    }
    return 0;
}

/* Embed the start s0 into the prepared QP, solve it, and take the step. info (out):
 * [max |step|, HPIPM iterations, HPIPM status, the heading residual at (X_0, u_0) (0 without
 * the term), 1 if the robust mode solved it, the embedding's defect]. The defect is
 * |f(s0, v0) - (f(s_lin, v0) + A0 (s0 - s_lin))|_inf (scaled units): how far stage 0
 * linearised at s_lin is from the stage itself at s0. Above max_defect nothing is solved and
 * the return is -2 (linearise at s0 instead). 0 on success, else HPIPM's status (the iterate
 * is then unchanged). */
int rti_feedback(void *handle, const double *s0, double *info, double max_defect) {
    rti_mem *m = handle;
    double ds[RTI_NS], e[RTI_NR];
    int moved = 0;
    for (int i = 0; i < RTI_NS; ++i) {
        ds[i] = s0[i] - m->s_lin[i];
        moved |= ds[i] != 0.0;
    }
    for (int i = 0; i < RTI_NS; ++i) { /* the linearised stage 0's gap at s0 */
        double acc = m->gap0[i];
        for (int j = 0; j < RTI_NS; ++j) acc += m->A0[i + j * RTI_NS] * ds[j];
        m->b[i] = acc;
    }
    double defect = 0.0; /* linearised next state (b + s_1) against the stage's own at s0 */
    if (moved) { /* the stage's next state (X, u) = (f(X_0, u_0), u_0): the model's step
                  * alone, without the stage's residuals and Jacobians */
        double next[RTI_NS];
        for (int i = 0; i < RTI_NU; ++i) next[RTI_NX + i] = s0[RTI_NX + i] + m->V[i];
        m->arg_ptr[0] = s0, m->arg_ptr[1] = next + RTI_NX;
        m->res_ptr[0] = next;
        rti_step(m->arg_ptr, m->res_ptr, m->iw, m->w, 0);
        for (int i = 0; i < RTI_NS; ++i) defect = fmax(defect, fabs(next[i] - m->b[i] - m->S[i]));
    }
    info[5] = defect;
    if (!(defect <= max_defect)) return -2;
    for (int l = 0; l < RTI_NR; ++l) {
        double acc = m->r0[l];
        for (int j = 0; j < RTI_NS; ++j) acc += m->Js0[l + j * RTI_NR] * ds[j];
        e[l] = acc;
    }
    tmul(RTI_NR, RTI_NU, 1, m->Jv0, e, m->rv);
    d_ocp_qp_set_b(0, m->b, &m->qp);
    d_ocp_qp_set_r(0, m->rv, &m->qp);
    if (RTI_NGH > 0) { /* the heading's gap at s0, to first order */
        for (int i = 0; i < RTI_NGH; ++i) {
            double acc = m->g0[i];
            for (int j = 0; j < RTI_NS; ++j) acc += m->Gs0[i + j * RTI_NG] * ds[j];
            m->lg[i] = -acc;
        }
        d_ocp_qp_set_lg(0, m->lg, &m->qp);
    }
    int status = 0, iter = 0, robust = 0;
    d_ocp_qp_ipm_solve(&m->qp, &m->sol, &m->arg[0], &m->ws[0]);
    d_ocp_qp_ipm_get_status(&m->ws[0], &status);
    d_ocp_qp_ipm_get_iter(&m->ws[0], &iter);
    if (status != 0) { /* e.g. stopped at the minimum step: once more, robustly */
        robust = 1;
        m->retries += 1;
        d_ocp_qp_ipm_solve(&m->qp, &m->sol, &m->arg[1], &m->ws[1]);
        d_ocp_qp_ipm_get_status(&m->ws[1], &status);
        int more = 0;
        d_ocp_qp_ipm_get_iter(&m->ws[1], &more);
        iter += more;
    }
    info[1] = iter, info[2] = status, info[4] = robust;
    if (status != 0) return status;
    for (int k = 0; k < RTI_N; ++k) { /* a non-finite step leaves the iterate as it was */
        d_ocp_qp_sol_get_u(k, &m->sol, m->step);
        if (!all_finite(RTI_NU, m->step)) return 3;
        d_ocp_qp_sol_get_x(k + 1, &m->sol, m->step);
        if (!all_finite(RTI_NS, m->step)) return 3;
    }
    double step_max = 0.0;
    for (int k = 0; k < RTI_N; ++k) {
        d_ocp_qp_sol_get_u(k, &m->sol, m->step);
        for (int i = 0; i < RTI_NU; ++i) {
            m->V[k * RTI_NU + i] += m->step[i];
            step_max = fmax(step_max, fabs(m->step[i]));
        }
        d_ocp_qp_sol_get_x(k + 1, &m->sol, m->step);
        for (int i = 0; i < RTI_NS; ++i) {
            m->S[k * RTI_NS + i] += m->step[i];
            step_max = fmax(step_max, fabs(m->step[i]));
        }
    }
    info[0] = step_max;
    info[3] = 0.0;
    if (RTI_HEADING) {
        double u0[RTI_NU], h = 0.0;
        for (int i = 0; i < RTI_NU; ++i) u0[i] = s0[RTI_NS - RTI_NU + i] + m->V[i];
        m->arg_ptr[0] = s0, m->arg_ptr[1] = u0;
        m->res_ptr[0] = &h;
        rti_heading(m->arg_ptr, m->res_ptr, m->iw, m->w, 0);
        info[3] = h;
    }
    return 0;
}

/* X_next = f(X, u), scaled: one step of the model */
void rti_predict(void *handle, const double *X, const double *u, double *X_next) {
    rti_mem *m = handle;
    m->arg_ptr[0] = X, m->arg_ptr[1] = u;
    m->res_ptr[0] = X_next;
    rti_step(m->arg_ptr, m->res_ptr, m->iw, m->w, 0);
}

/* the step damping mu >= 0 (the Levenberg-Marquardt term above); takes effect at the next
 * preparation */
void rti_set_damping(void *handle, double mu) { ((rti_mem *)handle)->reg = RTI_REG + mu; }

int rti_retries(void *handle) { return ((rti_mem *)handle)->retries; }

/* the fast mode's iteration limit alone (tests: a fast mode that stops short) */
void rti_set_fast_iter_max(void *handle, int iter_max) {
    d_ocp_qp_ipm_arg_set_iter_max(&iter_max, &((rti_mem *)handle)->arg[0]);
}
