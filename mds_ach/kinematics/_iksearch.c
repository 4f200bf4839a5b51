/* The IK searches of mds_ach.kinematics.ik in C: FK and analytic Jacobian of one serial arm, the task's error rows
 * and success score (the plain-float Task.residual_scalar, line for line), damped-least-squares steps with a trust
 * region and Levenberg-Marquardt damping, an active set at the joint limits, a null-space pull toward the seed, and
 * restarts from random joint vectors -- the whole solve in one call.
 *
 * Why C: in Python every step of a 6-joint search costs ~30-60 us of interpreter and numpy per-call overhead for
 * a few hundred floating-point operations; here a step takes ~1 us, so the restarts that a masked task with tight
 * wrist limits sometimes needs fit in a millisecond instead of tens. The chain (joint axes, offsets, tool point)
 * and the limits are handed over by the Python side from the URDF model (ArmKinematics.scalar_chain); nothing
 * about the MDS is written here. Optional: without a compiler the Python searches run (same steps, same tests).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#define MAXJ 8 /* joints per chain */
#define MAXR 6 /* task rows */
#define EXACT 1e-6 /* as ik.EXACT: at gimbal lock a pose this close counts as reached */
#define CREEP_WINDOW 5 /* as ik._CREEP_WINDOW / _CREEP_RATIO */
#define CREEP_RATIO 0.9
#define ACCEPT_SCALE 16.0 /* as ik._ACCEPT / _REJECT */
#define ACCEPT_DAMP 0.5
#define REJECT_SCALE 0.5
#define REJECT_DAMP 4.0

enum { POSITION = 0, EULER = 1, TILT = 2, FULL = 3 };

typedef struct {
    int n;
    int axis[MAXJ];
    double sign[MAXJ], t[MAXJ][3], tail[3];
    double lower[MAXJ], upper[MAXJ];
    int closed_form; /* the chain has the MDS shape (analytic.ArmGeometry): shoulder, upper arm, forearm, tool */
    double shoulder[3], L1, L2, d;
} Arm;

typedef struct {
    int mode, dof;
    int npos, pos_idx[3];
    double pos_t[3];
    int neul, eul_idx[3];
    double eul_t[3];
    double Rt[9], up[3];
    int nrot;
    double rot_t[3];
    double tol_pos, tol_ang, tol_mixed; /* tol_mixed <= 0: the separate test */
    int always_exact;
} Task;

typedef struct {
    double joint_step, task_step, max_joint_step, max_task_step, damping, null_gain;
    int stall;
} Steps;

/* A pose's error: rows e (r), their Jacobian (r x n), the solver's error and the score (<= 1 passes). */
typedef struct {
    int r;
    double e[MAXR], rows[MAXR][MAXJ], err, score;
} Residual;

static const int NEXT[3] = {1, 2, 0}, PREV[3] = {2, 0, 1};

/* Tool rotation R (row-major), position p and geometric Jacobian columns J[j] = (v, w) of joint vector q. */
static void fk_jacobian(const Arm *a, const double *q, double R[9], double p[3], double J[MAXJ][6]) {
    double r[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    double px = 0, py = 0, pz = 0, pts[MAXJ][3];
    for (int j = 0; j < a->n; j++) {
        const double *t = a->t[j];
        int k = a->axis[j];
        px += r[0] * t[0] + r[1] * t[1] + r[2] * t[2];
        py += r[3] * t[0] + r[4] * t[1] + r[5] * t[2];
        pz += r[6] * t[0] + r[7] * t[1] + r[8] * t[2];
        J[j][3] = a->sign[j] * r[k];
        J[j][4] = a->sign[j] * r[3 + k];
        J[j][5] = a->sign[j] * r[6 + k];
        pts[j][0] = px, pts[j][1] = py, pts[j][2] = pz;
        double c = cos(q[j]), s = a->sign[j] * sin(q[j]);
        int A = NEXT[k], B = PREV[k];
        for (int row = 0; row < 9; row += 3) {
            double ca = r[row + A], cb = r[row + B];
            r[row + A] = ca * c + cb * s;
            r[row + B] = cb * c - ca * s;
        }
    }
    const double *t = a->tail;
    px += r[0] * t[0] + r[1] * t[1] + r[2] * t[2];
    py += r[3] * t[0] + r[4] * t[1] + r[5] * t[2];
    pz += r[6] * t[0] + r[7] * t[1] + r[8] * t[2];
    for (int j = 0; j < a->n; j++) {
        double dx = px - pts[j][0], dy = py - pts[j][1], dz = pz - pts[j][2];
        double ax = J[j][3], ay = J[j][4], az = J[j][5];
        J[j][0] = ay * dz - az * dy;
        J[j][1] = az * dx - ax * dz;
        J[j][2] = ax * dy - ay * dx;
    }
    memcpy(R, r, sizeof r);
    p[0] = px, p[1] = py, p[2] = pz;
}

static double wrap(double x) { return remainder(x, 2.0 * M_PI); }

/* Task.residual_scalar, the same arithmetic in the same order (see its docstring for what each mode means). */
static void residual(const Arm *a, const Task *t, const double *q, Residual *out) {
    double R[9], p[3], J[MAXJ][6];
    int n = a->n, r = 0;
    fk_jacobian(a, q, R, p, J);
    double sq_pos = 0.0;
    for (int k = 0; k < t->npos; k++) {
        int i = t->pos_idx[k];
        double d = t->pos_t[k] - p[i];
        out->e[r] = d;
        for (int j = 0; j < n; j++)
            out->rows[r][j] = J[j][i];
        r++;
        sq_pos += d * d;
    }
    if (t->mode == POSITION) {
        out->r = r;
        out->err = sqrt(sq_pos);
        out->score = out->err / (t->tol_mixed > 0 ? t->tol_mixed : t->tol_pos);
        return;
    }
    double sq_rot = 0.0;
    if (t->mode == FULL) {
        const double *T = t->Rt;
        double M[9];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                M[3 * i + j] = T[3 * i] * R[3 * j] + T[3 * i + 1] * R[3 * j + 1] + T[3 * i + 2] * R[3 * j + 2];
        double vx = 0.5 * (M[7] - M[5]), vy = 0.5 * (M[2] - M[6]), vz = 0.5 * (M[3] - M[1]);
        double sin_t = sqrt(vx * vx + vy * vy + vz * vz), cos_t = 0.5 * (M[0] + M[4] + M[8] - 1.0);
        double theta = atan2(sin_t, cos_t), rv[3];
        if (sin_t < 1e-6 && cos_t < 0) { /* half-turn: the axis is the dominant column of M + I */
            int best = 0;
            double best_sq = -1.0;
            for (int c = 0; c < 3; c++) {
                double sq = 0.0;
                for (int i = 0; i < 3; i++) {
                    double b = M[3 * i + c] + (i == c);
                    sq += b * b;
                }
                if (sq > best_sq)
                    best_sq = sq, best = c;
            }
            double norm = sqrt(best_sq);
            for (int i = 0; i < 3; i++)
                rv[i] = (M[3 * i + best] + (i == best)) / norm * theta;
        } else {
            double f = sin_t > 1e-300 ? theta / sin_t : 1.0;
            rv[0] = vx * f, rv[1] = vy * f, rv[2] = vz * f;
        }
        for (int k = 0; k < 3; k++, r++) {
            out->e[r] = rv[k];
            for (int j = 0; j < n; j++)
                out->rows[r][j] = J[j][3 + k];
        }
        sq_rot = theta * theta;
    } else if (t->mode == TILT) {
        const double *b = t->up;
        double u[3] = {R[0] * b[0] + R[1] * b[1] + R[2] * b[2], R[3] * b[0] + R[4] * b[1] + R[5] * b[2],
                       R[6] * b[0] + R[7] * b[1] + R[8] * b[2]};
        double sin_t = hypot(u[0], u[1]), theta = atan2(sin_t, u[2]);
        if (sin_t > 1e-12) {
            out->e[r] = u[1] * theta / sin_t, out->e[r + 1] = -u[0] * theta / sin_t;
        } else {
            out->e[r] = u[2] < 0 ? M_PI : 0.0, out->e[r + 1] = 0.0;
        }
        out->e[r + 2] = 0.0;
        for (int j = 0; j < n; j++) {
            double along = u[0] * J[j][3] + u[1] * J[j][4] + u[2] * J[j][5];
            for (int k = 0; k < 3; k++)
                out->rows[r + k][j] = J[j][3 + k] - u[k] * along;
        }
        r += 3;
        sq_rot = theta * theta;
    }
    double angles[3] = {atan2(R[7], R[8]), atan2(-R[6], hypot(R[7], R[8])), atan2(R[3], R[0])};
    double sq_ang = 0.0;
    for (int k = 0; k < t->neul; k++, r++) {
        int i = t->eul_idx[k];
        double d = wrap(t->eul_t[k] - angles[i - 3]), g[3];
        out->e[r] = d;
        sq_ang += d * d;
        if (i == 3) { /* roll rate = (R00 wx + R10 wy) / cos^2(pitch) */
            double c2 = fmax(R[7] * R[7] + R[8] * R[8], 1e-12);
            g[0] = R[0] / c2, g[1] = R[3] / c2, g[2] = 0.0;
        } else if (i == 4) { /* pitch rate = (-R10 wx + R00 wy) / cos(pitch) */
            double c1 = sqrt(fmax(R[7] * R[7] + R[8] * R[8], 1e-12));
            g[0] = -R[3] / c1, g[1] = R[0] / c1, g[2] = 0.0;
        } else { /* yaw rate */
            double dd = fmax(R[0] * R[0] + R[3] * R[3], 1e-12);
            g[0] = -R[0] * R[6] / dd, g[1] = -R[3] * R[6] / dd, g[2] = 1.0;
        }
        for (int j = 0; j < n; j++)
            out->rows[r][j] = g[0] * J[j][3] + g[1] * J[j][4] + g[2] * J[j][5];
    }
    out->r = r;
    double err = sqrt(sq_pos + sq_ang + sq_rot);
    out->err = err;
    int mixed = t->tol_mixed > 0;
    if (!mixed && (t->mode == EULER || t->mode == FULL)) {
        out->score = fmax(sqrt(sq_pos) / t->tol_pos, sqrt(sq_ang + sq_rot) / t->tol_ang);
        return;
    }
    double angle = mixed ? err : sqrt(sq_ang + sq_rot);
    double bound = sqrt(3.0) * (mixed ? t->tol_mixed : t->tol_ang);
    if (t->mode != EULER && (t->always_exact || angle <= bound)) { /* else it cannot pass: see Task.residual */
        double d2 = 0.0;
        for (int k = 0; k < t->nrot; k++) {
            double d = wrap(t->rot_t[k] - angles[k]);
            d2 += d * d;
        }
        double exact = sqrt((mixed ? sq_pos : 0.0) + sq_ang + d2);
        angle = err <= EXACT ? fmin(angle, exact) : exact;
    }
    out->score = mixed ? angle / t->tol_mixed : fmax(sqrt(sq_pos) / t->tol_pos, angle / t->tol_ang);
}

/* Solve A X = B in place for a symmetric positive definite r x r A (damped, so it is) and m right-hand sides. */
static void cholesky_solve(int r, double A[MAXR][MAXR], int m, double B[2][MAXR]) {
    for (int j = 0; j < r; j++) {
        double d = A[j][j];
        for (int k = 0; k < j; k++)
            d -= A[j][k] * A[j][k];
        d = sqrt(fmax(d, 1e-300));
        A[j][j] = d;
        for (int i = j + 1; i < r; i++) {
            double s = A[i][j];
            for (int k = 0; k < j; k++)
                s -= A[i][k] * A[j][k];
            A[i][j] = s / d;
        }
    }
    for (int c = 0; c < m; c++) {
        double *b = B[c];
        for (int i = 0; i < r; i++) {
            for (int k = 0; k < i; k++)
                b[i] -= A[i][k] * b[k];
            b[i] /= A[i][i];
        }
        for (int i = r - 1; i >= 0; i--) {
            for (int k = i + 1; k < r; k++)
                b[i] -= A[k][i] * b[k];
            b[i] /= A[i][i];
        }
    }
}

static double now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* The state of one search: where it is, its residual, trust-region scale and damping. */
typedef struct {
    double q[MAXJ];
    Residual res;
    double scale, lam;
} Search;

/* One trust-region step (IKSolver._fast_search's loop body): propose, evaluate, keep it only if the error went
 * down. Returns whether the solver's error fell by more than 1e-4 of itself (progress, for the stall count). */
static int step(const Arm *a, const Task *t, const Steps *o, Search *s, const double *rest, double max_scale) {
    int n = a->n, r = s->res.r;
    const double *e = s->res.e;
    double Jf[MAXR][MAXJ], free_[MAXJ];
    for (int j = 0; j < n; j++) { /* active set: a joint at a limit pushed outward by J^T e is held */
        double g = 0.0;
        for (int i = 0; i < r; i++)
            g += e[i] * s->res.rows[i][j];
        free_[j] = (g < 0 ? s->q[j] <= a->lower[j] : s->q[j] >= a->upper[j]) ? 0.0 : 1.0;
    }
    for (int i = 0; i < r; i++)
        for (int j = 0; j < n; j++)
            Jf[i][j] = s->res.rows[i][j] * free_[j];
    double A[MAXR][MAXR];
    for (int i = 0; i < r; i++)
        for (int k = 0; k <= i; k++) {
            double v = 0.0;
            for (int j = 0; j < n; j++)
                v += Jf[i][j] * Jf[k][j];
            A[i][k] = A[k][i] = v;
        }
    for (int i = 0; i < r; i++)
        A[i][i] += s->lam * s->lam;
    double norm_e = 0.0;
    for (int i = 0; i < r; i++)
        norm_e += e[i] * e[i];
    norm_e = sqrt(norm_e);
    double cut = fmin(1.0, fmin(s->scale * o->task_step, o->max_task_step) / (norm_e + 1e-300));
    int null = t->dof < n && o->null_gain > 0;
    double B[2][MAXR], z[MAXJ], dq[MAXJ];
    for (int i = 0; i < r; i++)
        B[0][i] = e[i] * cut;
    if (null) {
        for (int j = 0; j < n; j++)
            z[j] = -o->null_gain * (s->q[j] - rest[j]) * free_[j];
        for (int i = 0; i < r; i++) {
            double v = 0.0;
            for (int j = 0; j < n; j++)
                v += Jf[i][j] * z[j];
            B[1][i] = v;
        }
    }
    cholesky_solve(r, A, null ? 2 : 1, B);
    double big = 0.0;
    for (int j = 0; j < n; j++) {
        double y0 = 0.0, y1 = 0.0;
        for (int i = 0; i < r; i++) {
            y0 += Jf[i][j] * B[0][i];
            if (null)
                y1 += Jf[i][j] * B[1][i];
        }
        dq[j] = null ? y0 + z[j] - y1 : y0;
        big = fmax(big, fabs(dq[j]));
    }
    double joint_limit = fmin(s->scale * o->joint_step, o->max_joint_step);
    double f = big > joint_limit ? joint_limit / big : 1.0;
    double q_new[MAXJ];
    for (int j = 0; j < n; j++)
        q_new[j] = fmin(fmax(s->q[j] + f * dq[j], a->lower[j]), a->upper[j]);
    Residual trial;
    residual(a, t, q_new, &trial);
    int progress = trial.err < s->res.err * (1.0 - 1e-4);
    if (trial.err < s->res.err) {
        memcpy(s->q, q_new, sizeof(double) * (size_t)n);
        s->res = trial;
        s->scale = fmin(s->scale * ACCEPT_SCALE, max_scale);
        s->lam = fmax(s->lam * ACCEPT_DAMP, o->damping);
    } else {
        s->scale = fmax(s->scale * REJECT_SCALE, 1e-4);
        s->lam = fmin(s->lam * REJECT_DAMP, 1.0);
    }
    return progress;
}

/* One search from s->q until the score is within tol, `budget` steps, `stall` steps without progress or (with
 * `creep`) an error that fell less than 10 % over 5 steps. Returns the steps taken. */
static long run_search(const Arm *a, const Task *t, const Steps *o, Search *s, const double *rest, long budget,
                       double tol, int stall, int creep, double max_scale) {
    double history[CREEP_WINDOW + 1];
    int since = 0, filled = 0;
    long it = 0;
    history[0] = s->res.err;
    filled = 1;
    while (s->res.score > tol && it < budget && since <= stall) {
        if (creep && filled > CREEP_WINDOW && history[(it) % (CREEP_WINDOW + 1)] >
                                                  CREEP_RATIO * history[(it + 1) % (CREEP_WINDOW + 1)])
            break; /* creeping: most likely a local minimum at the joint limits */
        double before = s->res.err;
        it++;
        since = step(a, t, o, s, rest, max_scale) ? 0 : since + 1;
        history[it % (CREEP_WINDOW + 1)] = fmin(s->res.err, before);
        if (filled <= CREEP_WINDOW)
            filled++;
    }
    return it;
}

/* splitmix64: the restarts' random joint vectors, from a state the caller keeps (reproducible solves). */
static uint64_t next_random(uint64_t *state) {
    uint64_t z = (*state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

static void start_search(const Arm *a, const Task *t, const Steps *o, Search *s, const double *q) {
    memcpy(s->q, q, sizeof(double) * (size_t)a->n);
    residual(a, t, s->q, &s->res);
    s->scale = 1.0;
    s->lam = o->damping;
}

/* ------------------------------------------------------------------------------------- closed form (6-DOF) */

/* analytic.ArmGeometry.solve: every joint vector with tool pose (R, p), up to 8, no limits applied. */
static int closed_form_solutions(const Arm *a, const double R[9], const double p[3], double out[8][MAXJ]) {
    double X[3] = {R[0], R[3], R[6]}, Y[3] = {R[1], R[4], R[7]}, Z[3] = {R[2], R[5], R[8]};
    double L1 = a->L1, L2 = a->L2, d = a->d, W[3], c[3];
    const double *S = a->shoulder;
    for (int i = 0; i < 3; i++)
        W[i] = p[i] + d * Z[i], c[i] = W[i] - S[i];
    double A = c[0] * Y[0] + c[1] * Y[1] + c[2] * Y[2], B = c[0] * Z[0] + c[1] * Z[1] + c[2] * Z[2];
    double k = (L1 * L1 - L2 * L2 - (c[0] * c[0] + c[1] * c[1] + c[2] * c[2])) / (2.0 * L2);
    double rho = hypot(A, B);
    if (rho < 1e-12 || fabs(k) > rho * (1.0 + 1e-12))
        return 0;
    double phi = atan2(A, B), delta = acos(fmax(-1.0, fmin(1.0, k / rho)));
    double q6s[2] = {phi + delta, phi - delta};
    int count = 0;
    for (int m = 0; m < (delta > 1e-12 ? 2 : 1); m++) {
        double q6 = delta > 1e-12 ? q6s[m] : phi, c6 = cos(q6), s6 = sin(q6), f[3], u[3], g2[3];
        for (int i = 0; i < 3; i++) {
            f[i] = s6 * Y[i] + c6 * Z[i]; /* forearm axis */
            u[i] = (S[i] - W[i] - L2 * f[i]) / L1; /* upper arm axis */
            g2[i] = c6 * Y[i] - s6 * Z[i];
        }
        double gu1 = X[0] * u[0] + X[1] * u[1] + X[2] * u[2], gu2 = g2[0] * u[0] + g2[1] * u[1] + g2[2] * u[2];
        if (hypot(gu1, gu2) < 1e-9)
            continue; /* straight elbow: the swivel is free (outside the MDS limits) */
        double q5a = atan2(-gu2, gu1);
        for (int h = 0; h < 2; h++) {
            double q5 = h ? q5a + M_PI : q5a, c5 = cos(q5), s5 = sin(q5), ex[3], ey[3];
            for (int i = 0; i < 3; i++)
                ex[i] = c5 * X[i] - s5 * g2[i], ey[i] = s5 * X[i] + c5 * g2[i];
            double q4 = atan2(-(u[0] * ex[0] + u[1] * ex[1] + u[2] * ex[2]), u[0] * f[0] + u[1] * f[1] + u[2] * f[2]);
            double mx1 = cos(q4) * ex[1] + sin(q4) * f[1];
            double q1 = atan2(u[0], u[2]), q2 = atan2(-u[1], hypot(mx1, ey[1])), q3 = atan2(mx1, ey[1]);
            double tail[3] = {q4, wrap(q5), wrap(q6)};
            double *x = out[count++], *y = out[count++];
            x[0] = q1, x[1] = q2, x[2] = q3;
            y[0] = wrap(q1 + M_PI), y[1] = wrap(M_PI - q2), y[2] = wrap(q3 + M_PI);
            memcpy(x + 3, tail, sizeof tail);
            memcpy(y + 3, tail, sizeof tail);
        }
    }
    return count;
}

/* analytic.within: q moved into the limits by whole turns where possible (clamped within 1e-9); 0 if not. */
static int within_limits(const Arm *a, double *q) {
    const double slack = 1e-9, turn = 2.0 * M_PI;
    for (int j = 0; j < a->n; j++) {
        double v = q[j], lo = a->lower[j], hi = a->upper[j];
        if (v < lo - slack)
            v += turn * ceil((lo - slack - v) / turn);
        else if (v > hi + slack)
            v -= turn * ceil((v - hi - slack) / turn);
        if (!(lo - slack <= v && v <= hi + slack))
            return 0;
        q[j] = fmin(fmax(v, lo), hi);
    }
    return 1;
}

static double max_distance(const double *q, const double *seed, int n) {
    double m = 0.0;
    for (int j = 0; j < n; j++)
        m = fmax(m, fabs(q[j] - seed[j]));
    return m;
}

/* IKSolver._closed_form's candidates: the seed itself when it is already there, then the exact solutions within
 * the limits nearest the seed first (max joint distance, stable), each kept only if its score is within 1e-3. */
static int closed_form_candidates(const Arm *a, const Task *t, const double *seed, double out[9][MAXJ]) {
    double sol[8][MAXJ], p[3] = {0, 0, 0}, key[9];
    for (int k = 0; k < t->npos; k++)
        p[t->pos_idx[k]] = t->pos_t[k];
    int m = closed_form_solutions(a, t->Rt, p, sol), count = 0;
    Residual res;
    residual(a, t, seed, &res);
    if (res.score <= 1e-3)
        memcpy(out[count], seed, sizeof(double) * (size_t)a->n), key[count++] = -1.0;
    for (int i = 0; i < m; i++) {
        if (!within_limits(a, sol[i]))
            continue;
        residual(a, t, sol[i], &res);
        if (res.score > 1e-3)
            continue; /* clamped at a limit beyond the tolerance (or a round-off case) */
        double dist = max_distance(sol[i], seed, a->n);
        int at = count;
        while (at > 0 && key[at - 1] > dist) { /* insertion: stable, like Python's sort */
            memcpy(out[at], out[at - 1], sizeof(double) * MAXJ);
            key[at] = key[at - 1];
            at--;
        }
        memcpy(out[at], sol[i], sizeof(double) * (size_t)a->n);
        key[at] = dist;
        count++;
    }
    return count;
}

/* The original's error at q (Task.error: the mixed m+rad test at tolerance 1, Euler differences always worked out)
 * and the six components [x, y, z, roll, pitch, yaw] of the pose reached: what IKSolver's result reports. */
static void report_at(const Arm *a, const Task *t, const double *q, double *error, double pose[6]) {
    Task legacy = *t;
    legacy.tol_mixed = 1.0;
    legacy.always_exact = 1;
    Residual res;
    residual(a, &legacy, q, &res);
    *error = res.score;
    double R[9], p[3], J[MAXJ][6];
    fk_jacobian(a, q, R, p, J);
    pose[0] = p[0], pose[1] = p[1], pose[2] = p[2];
    pose[3] = atan2(R[7], R[8]), pose[4] = atan2(-R[6], hypot(R[7], R[8])), pose[5] = atan2(R[3], R[0]);
}

/* ------------------------------------------------------------------------------------------- Python glue */

static void arm_free(PyObject *cap) { PyMem_Free(PyCapsule_GetPointer(cap, "mds_iksearch.Arm")); }

/* Read exactly `n` floats (n < 0: up to -n, count returned) from a sequence into out. */
static int floats(PyObject *obj, double *out, int n, const char *what) {
    PyObject *seq = PySequence_Fast(obj, what);
    if (seq == NULL)
        return -1;
    Py_ssize_t len = PySequence_Fast_GET_SIZE(seq);
    if ((n >= 0 && len != n) || (n < 0 && len > -n)) {
        PyErr_Format(PyExc_ValueError, "_iksearch: %s needs %d numbers, got %zd", what, n < 0 ? -n : n, len);
        Py_DECREF(seq);
        return -1;
    }
    for (Py_ssize_t i = 0; i < len; i++) {
        out[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(seq, i));
        if (out[i] == -1.0 && PyErr_Occurred()) {
            Py_DECREF(seq);
            return -1;
        }
    }
    Py_DECREF(seq);
    return (int)len;
}

static int ints(PyObject *obj, int *out, int max, const char *what) {
    double v[MAXJ];
    int len = floats(obj, v, -max, what);
    for (int i = 0; i < len; i++)
        out[i] = (int)v[i];
    return len;
}

/* arm(axes, signs, offsets (n*3), tail (3), lower, upper[, geometry]) -> handle; geometry (analytic.ArmGeometry:
 * shoulder x, y, z, upper arm, forearm, tool offset) enables closed_form. */
static PyObject *py_arm(PyObject *self, PyObject *args) {
    PyObject *axes, *signs, *offsets, *tail, *lower, *upper, *geometry = Py_None;
    if (!PyArg_ParseTuple(args, "OOOOOO|O", &axes, &signs, &offsets, &tail, &lower, &upper, &geometry))
        return NULL;
    Arm *a = PyMem_Calloc(1, sizeof(Arm));
    if (a == NULL)
        return PyErr_NoMemory();
    double flat[3 * MAXJ];
    int n = ints(axes, a->axis, MAXJ, "axes");
    if (n < 0 || floats(signs, a->sign, n, "signs") < 0 || floats(offsets, flat, 3 * n, "offsets") < 0 ||
        floats(tail, a->tail, 3, "tail") < 0 || floats(lower, a->lower, n, "lower") < 0 ||
        floats(upper, a->upper, n, "upper") < 0) {
        PyMem_Free(a);
        return NULL;
    }
    a->n = n;
    for (int j = 0; j < n; j++) {
        if (a->axis[j] < 0 || a->axis[j] > 2 || !(a->lower[j] <= a->upper[j])) {
            PyMem_Free(a);
            return PyErr_Format(PyExc_ValueError, "_iksearch.arm: joint %d: axis must be 0..2, lower <= upper", j);
        }
        memcpy(a->t[j], flat + 3 * j, sizeof(double) * 3);
    }
    if (geometry != Py_None) {
        double g[6];
        if (floats(geometry, g, 6, "geometry") < 0) {
            PyMem_Free(a);
            return NULL;
        }
        if (n != 6 || !(g[3] > 0 && g[4] > 0)) {
            PyMem_Free(a);
            return PyErr_Format(PyExc_ValueError, "_iksearch.arm: the closed form needs 6 joints and lengths > 0");
        }
        a->closed_form = 1;
        memcpy(a->shoulder, g, sizeof(double) * 3);
        a->L1 = g[3], a->L2 = g[4], a->d = g[5];
    }
    PyObject *cap = PyCapsule_New(a, "mds_iksearch.Arm", arm_free);
    if (cap == NULL)
        PyMem_Free(a);
    return cap;
}

/* The task tuple (ik.Task._native_spec): mode, pos_idx, pos_target, euler_idx, euler_target, R_target (9 or
 * empty), up (3 or empty), rotation_target, tol_pos, tol_angle, tol_mixed (0: none), always_exact. */
static int parse_task(PyObject *spec, Task *t) {
    PyObject *pi, *pt, *ei, *et, *Rt, *up, *rt;
    memset(t, 0, sizeof *t);
    if (!PyArg_ParseTuple(spec, "iOOOOOOOdddp", &t->mode, &pi, &pt, &ei, &et, &Rt, &up, &rt, &t->tol_pos,
                          &t->tol_ang, &t->tol_mixed, &t->always_exact))
        return -1;
    int nR, nup;
    if ((t->npos = ints(pi, t->pos_idx, 3, "pos_idx")) < 0 || floats(pt, t->pos_t, t->npos, "pos_target") < 0 ||
        (t->neul = ints(ei, t->eul_idx, 3, "euler_idx")) < 0 || floats(et, t->eul_t, t->neul, "euler_target") < 0 ||
        (nR = floats(Rt, t->Rt, -9, "R_target")) < 0 || (nup = floats(up, t->up, -3, "up")) < 0 ||
        (t->nrot = floats(rt, t->rot_t, -3, "rotation_target")) < 0)
        return -1;
    if ((t->mode == FULL) != (nR == 9) || (t->mode == TILT) != (nup == 3) ||
        t->nrot != (t->mode == FULL ? 3 : t->mode == TILT ? 2 : 0))
        return PyErr_Format(PyExc_ValueError, "_iksearch: task mode %d needs R_target (full pose), up (tilt) and "
                            "rotation_target (3 or 2 values) to match, got %d, %d, %d values", t->mode, nR, nup,
                            t->nrot), -1;
    if (!(t->tol_pos > 0 && t->tol_ang > 0 && t->tol_mixed >= 0))
        return PyErr_Format(PyExc_ValueError, "_iksearch: tolerances must be > 0"), -1;
    for (int k = 0; k < t->npos; k++)
        if (t->pos_idx[k] < 0 || t->pos_idx[k] > 2)
            return PyErr_Format(PyExc_ValueError, "_iksearch: position index %d", t->pos_idx[k]), -1;
    for (int k = 0; k < t->neul; k++)
        if (t->eul_idx[k] < 3 || t->eul_idx[k] > 5)
            return PyErr_Format(PyExc_ValueError, "_iksearch: angle index %d", t->eul_idx[k]), -1;
    if (t->mode < POSITION || t->mode > FULL)
        return PyErr_Format(PyExc_ValueError, "_iksearch: task mode %d", t->mode), -1;
    t->dof = t->npos + t->neul + (t->mode == FULL ? 3 : t->mode == TILT ? 2 : 0);
    return 0;
}

static int parse_steps(PyObject *spec, Steps *o) {
    return PyArg_ParseTuple(spec, "ddddddi", &o->joint_step, &o->task_step, &o->max_joint_step, &o->max_task_step,
                            &o->damping, &o->null_gain, &o->stall)
               ? 0
               : -1;
}

static PyObject *joint_list(const double *q, int n) {
    PyObject *out = PyList_New(n);
    if (out == NULL)
        return NULL;
    for (int j = 0; j < n; j++) {
        PyObject *v = PyFloat_FromDouble(q[j]);
        if (v == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, j, v);
    }
    return out;
}

static double max_scale_of(const Steps *o) {
    return fmax(fmax(o->max_joint_step / o->joint_step, o->max_task_step / o->task_step), 1.0);
}

/* search(arm, task, steps, start, rest, budget, tol, scale, stall, creep) -> (q, score, err, steps, converged):
 * one search (IKSolver._fast_search). */
static PyObject *py_search(PyObject *self, PyObject *args) {
    PyObject *cap, *task_spec, *steps_spec, *start_obj, *rest_obj;
    long budget;
    double tol, scale;
    int stall, creep;
    if (!PyArg_ParseTuple(args, "OOOOOlddip", &cap, &task_spec, &steps_spec, &start_obj, &rest_obj, &budget, &tol,
                          &scale, &stall, &creep))
        return NULL;
    Arm *a = PyCapsule_GetPointer(cap, "mds_iksearch.Arm");
    Task t;
    Steps o;
    double start[MAXJ], rest[MAXJ];
    if (a == NULL || parse_task(task_spec, &t) < 0 || parse_steps(steps_spec, &o) < 0 ||
        floats(start_obj, start, a->n, "start") < 0 || floats(rest_obj, rest, a->n, "rest") < 0)
        return NULL;
    Search s;
    long it;
    Py_BEGIN_ALLOW_THREADS
    start_search(a, &t, &o, &s, start);
    s.scale = scale;
    it = run_search(a, &t, &o, &s, rest, budget, tol, stall, creep, max_scale_of(&o));
    Py_END_ALLOW_THREADS
    return Py_BuildValue("(NddlO)", joint_list(s.q, a->n), s.res.score, s.res.err, it,
                         s.res.score <= tol ? Py_True : Py_False);
}

/* solve(arm, task, steps, seed, from_seed, fast, per_start, budget, timeout, polish, rng_state)
 *   -> (q, score, err, steps, restarts, converged, rng_state, original's error at q, [x, y, z, roll, pitch, yaw] at q)
 *
 * From the seed (when from_seed): a search that stops when it creeps (`fast` steps at most), then the same search
 * on without that test until it stalls (`per_start` steps at most); then searches from random joint vectors within
 * the limits, one after another, until one converges, `budget` steps were taken or `timeout` seconds passed
 * (<= 0: none). A solution then gets up to `polish` more steps toward 1/1000 of the tolerance (kept if better).
 * On failure q is the pose of the lowest solver error seen. The null-space pull is toward the seed throughout. */
static PyObject *py_solve(PyObject *self, PyObject *args) {
    PyObject *cap, *task_spec, *steps_spec, *seed_obj;
    int from_seed, polish;
    long fast, per_start, budget;
    double timeout;
    unsigned long long rng;
    if (!PyArg_ParseTuple(args, "OOOOpllldiK", &cap, &task_spec, &steps_spec, &seed_obj, &from_seed, &fast,
                          &per_start, &budget, &timeout, &polish, &rng))
        return NULL;
    Arm *a = PyCapsule_GetPointer(cap, "mds_iksearch.Arm");
    Task t;
    Steps o;
    double seed[MAXJ];
    if (a == NULL || parse_task(task_spec, &t) < 0 || parse_steps(steps_spec, &o) < 0 ||
        floats(seed_obj, seed, a->n, "seed") < 0)
        return NULL;
    int n = a->n, converged = 0;
    long used = 0, restarts = 0;
    uint64_t state = rng;
    double best_q[MAXJ], best_err = INFINITY, best_score = INFINITY, max_scale = max_scale_of(&o);
    Search s;
    double error, pose[6];
    Py_BEGIN_ALLOW_THREADS
    double deadline = timeout > 0 ? now() + timeout : INFINITY;
    memcpy(best_q, seed, sizeof(double) * (size_t)n);
    if (from_seed) {
        start_search(a, &t, &o, &s, seed);
        used += run_search(a, &t, &o, &s, seed, fast < budget ? fast : budget, 1.0, o.stall < 10 ? o.stall : 10,
                           1, max_scale);
        if (s.res.score > 1.0 && used < budget)
            used += run_search(a, &t, &o, &s, seed, per_start < budget - used ? per_start : budget - used, 1.0,
                               o.stall, 0, max_scale);
        converged = s.res.score <= 1.0;
        best_err = s.res.err, best_score = s.res.score;
        memcpy(best_q, s.q, sizeof(double) * (size_t)n);
    }
    while (!converged && used < budget && now() < deadline) {
        double q[MAXJ];
        for (int j = 0; j < n; j++) {
            double u = (double)(next_random(&state) >> 11) * 0x1.0p-53;
            q[j] = a->lower[j] + u * (a->upper[j] - a->lower[j]);
        }
        restarts++;
        start_search(a, &t, &o, &s, q);
        used += run_search(a, &t, &o, &s, seed, per_start < budget - used ? per_start : budget - used, 1.0, o.stall,
                           1, max_scale);
        converged = s.res.score <= 1.0;
        if (converged || s.res.err < best_err) {
            best_err = s.res.err, best_score = s.res.score;
            memcpy(best_q, s.q, sizeof(double) * (size_t)n);
        }
    }
    if (polish > budget - used)  /* the polish is part of the step budget (max_iterations * seeds), never beyond it */
        polish = (int)(budget - used);
    if (converged && polish > 0 && s.res.score > 1e-3) { /* the original stopped at 1 cm: a little better is cheap */
        Search p = s;
        p.scale = max_scale;
        used += run_search(a, &t, &o, &p, seed, polish, 1e-3, o.stall < 10 ? o.stall : 10, 1, max_scale);
        if (p.res.score < s.res.score) {
            best_err = p.res.err, best_score = p.res.score;
            memcpy(best_q, p.q, sizeof(double) * (size_t)n);
        }
    }
    report_at(a, &t, best_q, &error, pose);
    Py_END_ALLOW_THREADS
    return Py_BuildValue("(NddllOKdN)", joint_list(best_q, n), best_score, best_err, used, restarts,
                         converged ? Py_True : Py_False, (unsigned long long)state, error, joint_list(pose, 6));
}

/* closed_form(arm, task, seed) -> [(q, original's error, pose components), ...]: IKSolver._closed_form's
 * candidates in its order (the seed if already there, then nearest first), for a full-pose task. */
static PyObject *py_closed_form(PyObject *self, PyObject *args) {
    PyObject *cap, *task_spec, *seed_obj;
    if (!PyArg_ParseTuple(args, "OOO", &cap, &task_spec, &seed_obj))
        return NULL;
    Arm *a = PyCapsule_GetPointer(cap, "mds_iksearch.Arm");
    Task t;
    double seed[MAXJ];
    if (a == NULL || parse_task(task_spec, &t) < 0 || floats(seed_obj, seed, a->n, "seed") < 0)
        return NULL;
    if (!a->closed_form || t.mode != FULL || t.npos != 3)
        return PyErr_Format(PyExc_ValueError, "_iksearch.closed_form: needs an arm of the MDS shape and a full pose");
    double found[9][MAXJ], errors[9], poses[9][6];
    int count = closed_form_candidates(a, &t, seed, found);
    for (int i = 0; i < count; i++)
        report_at(a, &t, found[i], &errors[i], poses[i]);
    PyObject *out = PyList_New(count);
    for (int i = 0; out != NULL && i < count; i++) {
        PyObject *item = Py_BuildValue("(NdN)", joint_list(found[i], a->n), errors[i], joint_list(poses[i], 6));
        if (item == NULL) {
            Py_CLEAR(out);
            break;
        }
        PyList_SET_ITEM(out, i, item);
    }
    return out;
}

static PyMethodDef methods[] = {
    {"closed_form", py_closed_form, METH_VARARGS, "The closed-form full-pose candidates (see the C source)."},
    {"arm", py_arm, METH_VARARGS, "arm(axes, signs, offsets, tail, lower, upper) -> handle of a serial chain"},
    {"search", py_search, METH_VARARGS, "One damped-least-squares search (see the C source)."},
    {"solve", py_solve, METH_VARARGS, "A whole IK solve: the seed's search, then restarts (see the C source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_iksearch",
                                    "The IK searches of mds_ach.kinematics.ik in C (optional fast path).", -1,
                                    methods};

PyMODINIT_FUNC PyInit__iksearch(void) {
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && (PyModule_AddIntConstant(m, "MAX_JOINTS", MAXJ) < 0)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
