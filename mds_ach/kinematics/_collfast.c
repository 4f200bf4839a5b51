/* The collision gate's per-configuration screen, in C: joint frames, primitive poses and a per-pair test on the
 * inflated primitives that is exact where the geometry is simple (sphere-sphere, sphere-box, sphere-cylinder,
 * box-box by the separating-axis test) and conservative elsewhere (anything with a box or cylinder against a
 * cylinder: separated only when the bounding boxes, or the cylinders' capsules, are).
 *
 * Why C: the numpy path costs ~100 us per configuration, nearly all of it per-call overhead of small arrays
 * (FK level by level, the broad phase); the same arithmetic here takes ~2 us. python-fcl stays the judge of every
 * pair this screen cannot decide (within eps of touching) and of every clearance it cannot certify, so answers
 * are those of python-fcl. check_one/check_many build the answer objects (CheckResult, Contact) here too.
 * Optional: without a compiler, mds_ach.kinematics.collision runs the numpy path (same answers, slower).
 *
 * Status of a pair: 0 = apart by more than eps (certain), 1 = undecided (ask fcl), 2 = overlapping by more than
 * eps (certain). eps keeps near-touching pairs, where two algorithms may round differently, with fcl.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

enum { SPHERE = 0, BOX = 1, CYLINDER = 2 };

#define GJK_TOL 1e-9  /* m: a GJK or EPA distance is within this of the true one */
#define GJK_RESTARTS 2  /* new simplices when GJK stalls short of GJK_TOL on shapes apart */

/* A 3x4 affine transform, row-major: R (3x3) and t in the last column. */
typedef double Affine[12];

typedef struct {
    Py_ssize_t n, P, M;
    double eps;
    double *A;          /* n * 3 * 12: joint i local = A0 + sin(q) A1 + (1 - cos(q)) A2 */
    int64_t *parent;    /* n: parent joint index, n = root */
    int64_t *order;     /* n: joints, parents first */
    int64_t *owner;     /* P: joint that moves the primitive, n = fixed */
    double *offset;     /* P * 12 */
    int64_t *kind;      /* P */
    double *dims;       /* P * 3: sphere (r), box (half x, y, z), cylinder (r, half length) -- inflated */
    double *raw;        /* P * 3: the same, un-inflated (for clearances) */
    double *brad;       /* P: bounding radius about the centre */
    double *pad;        /* P: how far the inflation moved every side of the primitive out (least) */
    double *padmax;     /* P: the same, most */
    int64_t *I, *J;     /* M pairs */
    double *T;          /* (n + 1) * 12 work: joint frames */
    double *W;          /* P * 12 work: primitive poses */
    double *poses;      /* P * 16 work: the same as 4 x 4 */
    PyObject *contact;  /* the Contact class, and per pair the dict of its fields (clearance set per contact) */
    PyObject *fields;   /* tuple of M dicts */
    PyObject *result;   /* the CheckResult class, and its instance without contacts; all four NULL until contacts() */
    PyObject *free;
} Model;

static void model_free(Model *m) {
    if (m == NULL)
        return;
    PyMem_Free(m->A); PyMem_Free(m->parent); PyMem_Free(m->order); PyMem_Free(m->owner);
    PyMem_Free(m->offset); PyMem_Free(m->kind); PyMem_Free(m->dims); PyMem_Free(m->raw); PyMem_Free(m->brad); PyMem_Free(m->pad); PyMem_Free(m->padmax);
    PyMem_Free(m->I); PyMem_Free(m->J); PyMem_Free(m->T); PyMem_Free(m->W); PyMem_Free(m->poses);
    Py_XDECREF(m->contact); Py_XDECREF(m->fields); Py_XDECREF(m->result); Py_XDECREF(m->free);
    PyMem_Free(m);
}

static void capsule_free(PyObject *cap) {
    model_free((Model *)PyCapsule_GetPointer(cap, "mds_collfast.Model"));
}

/* Copy a contiguous buffer of `count` items of `itemsize` bytes (checked) into fresh memory. */
static int copy_buffer(PyObject *obj, Py_ssize_t count, Py_ssize_t itemsize, void **out, const char *what) {
    Py_buffer view;
    if (PyObject_GetBuffer(obj, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    if (view.itemsize != itemsize || view.len != count * itemsize) {
        PyErr_Format(PyExc_ValueError, "_collfast.build: %s needs %zd items of %zd bytes, got %zd bytes of %zd",
                     what, count, itemsize, view.len, view.itemsize);
        PyBuffer_Release(&view);
        return -1;
    }
    *out = PyMem_Malloc(count > 0 ? count * itemsize : 1);
    if (*out == NULL) {
        PyBuffer_Release(&view);
        PyErr_NoMemory();
        return -1;
    }
    memcpy(*out, view.buf, count * itemsize);
    PyBuffer_Release(&view);
    return 0;
}

/* build(n, P, M, eps, A, parent, order, owner, offset, kind, dims, raw, brad, I, J) -> handle */
static PyObject *build(PyObject *self, PyObject *args) {
    Py_ssize_t n, P, M;
    double eps;
    PyObject *A, *parent, *order, *owner, *offset, *kind, *dims, *raw, *brad, *I, *J;
    if (!PyArg_ParseTuple(args, "nnndOOOOOOOOOOO", &n, &P, &M, &eps, &A, &parent, &order, &owner, &offset, &kind,
                          &dims, &raw, &brad, &I, &J))
        return NULL;
    if (n < 0 || P < 0 || M < 0) {
        PyErr_SetString(PyExc_ValueError, "_collfast.build: negative size");
        return NULL;
    }
    Model *m = PyMem_Calloc(1, sizeof(Model));
    if (m == NULL)
        return PyErr_NoMemory();
    m->n = n; m->P = P; m->M = M; m->eps = eps;
    if (copy_buffer(A, n * 36, 8, (void **)&m->A, "A") < 0 || copy_buffer(parent, n, 8, (void **)&m->parent, "parent") < 0
        || copy_buffer(order, n, 8, (void **)&m->order, "order") < 0
        || copy_buffer(owner, P, 8, (void **)&m->owner, "owner") < 0
        || copy_buffer(offset, P * 12, 8, (void **)&m->offset, "offset") < 0
        || copy_buffer(kind, P, 8, (void **)&m->kind, "kind") < 0
        || copy_buffer(dims, P * 3, 8, (void **)&m->dims, "dims") < 0
        || copy_buffer(raw, P * 3, 8, (void **)&m->raw, "raw") < 0
        || copy_buffer(brad, P, 8, (void **)&m->brad, "brad") < 0
        || copy_buffer(I, M, 8, (void **)&m->I, "I") < 0 || copy_buffer(J, M, 8, (void **)&m->J, "J") < 0) {
        model_free(m);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        if (m->parent[i] < 0 || m->parent[i] > n || m->order[i] < 0 || m->order[i] >= n) {
            model_free(m);
            PyErr_SetString(PyExc_ValueError, "_collfast.build: joint index out of range");
            return NULL;
        }
    }
    for (Py_ssize_t p = 0; p < P; p++) {
        if (m->owner[p] < 0 || m->owner[p] > n || m->kind[p] < SPHERE || m->kind[p] > CYLINDER) {
            model_free(m);
            PyErr_SetString(PyExc_ValueError, "_collfast.build: primitive owner or kind out of range");
            return NULL;
        }
    }
    for (Py_ssize_t k = 0; k < M; k++) {
        if (m->I[k] < 0 || m->I[k] >= P || m->J[k] < 0 || m->J[k] >= P) {
            model_free(m);
            PyErr_SetString(PyExc_ValueError, "_collfast.build: pair index out of range");
            return NULL;
        }
    }
    m->T = PyMem_Malloc((n + 1) * 12 * sizeof(double));
    m->W = PyMem_Malloc((P > 0 ? P : 1) * 12 * sizeof(double));
    m->pad = PyMem_Malloc((P > 0 ? P : 1) * sizeof(double));
    m->padmax = PyMem_Malloc((P > 0 ? P : 1) * sizeof(double));
    m->poses = PyMem_Malloc((P > 0 ? P : 1) * 16 * sizeof(double));
    if (m->T == NULL || m->W == NULL || m->pad == NULL || m->padmax == NULL || m->poses == NULL) {
        model_free(m);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t p = 0; p < P; p++) {  /* the smallest side move: sphere r; box x, y, z; cylinder r, length */
        const int used = m->kind[p] == SPHERE ? 1 : (m->kind[p] == BOX ? 3 : 2);
        double pad = INFINITY, padmax = -INFINITY;
        for (int k = 0; k < used; k++) {
            pad = fmin(pad, m->dims[3 * p + k] - m->raw[3 * p + k]);
            padmax = fmax(padmax, m->dims[3 * p + k] - m->raw[3 * p + k]);
        }
        m->pad[p] = pad;
        m->padmax[p] = padmax;
    }
    PyObject *cap = PyCapsule_New(m, "mds_collfast.Model", capsule_free);
    if (cap == NULL)
        model_free(m);
    return cap;
}

/* c = a @ b for affine transforms */
static inline void compose(const double *a, const double *b, double *c) {
    for (int r = 0; r < 3; r++) {
        const double a0 = a[4 * r], a1 = a[4 * r + 1], a2 = a[4 * r + 2];
        c[4 * r] = a0 * b[0] + a1 * b[4] + a2 * b[8];
        c[4 * r + 1] = a0 * b[1] + a1 * b[5] + a2 * b[9];
        c[4 * r + 2] = a0 * b[2] + a1 * b[6] + a2 * b[10];
        c[4 * r + 3] = a0 * b[3] + a1 * b[7] + a2 * b[11] + a[4 * r + 3];
    }
}

static inline double dot3(const double *u, const double *v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

/* Column k of the rotation of affine T. */
static inline void axis(const double *T, int k, double *out) {
    out[0] = T[k]; out[1] = T[4 + k]; out[2] = T[8 + k];
}

static inline void centre(const double *T, double *out) {
    out[0] = T[3]; out[1] = T[7]; out[2] = T[11];
}

/* Point in the local frame of T: R^T (p - t). */
static inline void to_local(const double *T, const double *p, double *out) {
    const double d[3] = {p[0] - T[3], p[1] - T[7], p[2] - T[11]};
    out[0] = T[0] * d[0] + T[4] * d[1] + T[8] * d[2];
    out[1] = T[1] * d[0] + T[5] * d[1] + T[9] * d[2];
    out[2] = T[2] * d[0] + T[6] * d[1] + T[10] * d[2];
}

static inline int classify(double d, double eps) { return d > eps ? 0 : (d < -eps ? 2 : 1); }

/* Signed distance of a point (local coordinates) to a solid box of half extents h. */
static double point_box(const double *p, const double *h) {
    double out2 = 0.0, inside = -INFINITY;
    for (int k = 0; k < 3; k++) {
        const double e = fabs(p[k]) - h[k];
        if (e > 0)
            out2 += e * e;
        if (e > inside)
            inside = e;
    }
    return out2 > 0 ? sqrt(out2) : inside;
}

/* Signed distance of a point (local coordinates) to a solid cylinder (radius r, half length h along z). */
static double point_cylinder(const double *p, double r, double h) {
    const double er = hypot(p[0], p[1]) - r, ez = fabs(p[2]) - h;
    if (er > 0 || ez > 0) {
        const double a = er > 0 ? er : 0.0, b = ez > 0 ? ez : 0.0;
        return hypot(a, b);
    }
    return er > ez ? er : ez;
}

/* Separating-axis test of two oriented boxes (frames Ta, Tb, half extents ha, hb): 0 apart by more than eps on
 * some axis, 2 overlapping by more than eps on all (then they intersect), else 1. Axes from parallel edges
 * (zero cross product) are skipped: the face axes cover that case. */
static int obb_obb(const double *Ta, const double *ha, const double *Tb, const double *hb, double eps) {
    double a[3][3], b[3][3], d[3], ca[3], cb[3];
    for (int k = 0; k < 3; k++) {
        axis(Ta, k, a[k]);
        axis(Tb, k, b[k]);
    }
    centre(Ta, ca);
    centre(Tb, cb);
    for (int k = 0; k < 3; k++)
        d[k] = cb[k] - ca[k];
    int sure = 1;
    double L[3];
    for (int t = 0; t < 15; t++) {
        if (t < 3) {
            memcpy(L, a[t], sizeof L);
        } else if (t < 6) {
            memcpy(L, b[t - 3], sizeof L);
        } else {
            const double *u = a[(t - 6) / 3], *v = b[(t - 6) % 3];
            L[0] = u[1] * v[2] - u[2] * v[1];
            L[1] = u[2] * v[0] - u[0] * v[2];
            L[2] = u[0] * v[1] - u[1] * v[0];
        }
        const double len = sqrt(dot3(L, L));
        if (len < 1e-9)
            continue;
        double ra = 0.0, rb = 0.0;
        for (int k = 0; k < 3; k++) {
            ra += ha[k] * fabs(dot3(a[k], L));
            rb += hb[k] * fabs(dot3(b[k], L));
        }
        const double gap = (fabs(dot3(d, L)) - ra - rb) / len;
        if (gap > eps)
            return 0;
        if (gap >= -eps)
            sure = 0;
    }
    return sure ? 2 : 1;
}

/* Squared distance between segments p0 + s u and q0 + t v, s, t in [-1, 1] (u, v: half-length vectors). */
static double segment_segment2(const double *p0, const double *u, const double *q0, const double *v) {
    const double w[3] = {p0[0] - q0[0], p0[1] - q0[1], p0[2] - q0[2]};
    const double a = dot3(u, u), b = dot3(u, v), c = dot3(v, v), d = dot3(u, w), e = dot3(v, w);
    const double den = a * c - b * b;
    double s = den > 1e-12 * a * c ? (b * e - c * d) / den : 0.0;
    s = s < -1 ? -1 : (s > 1 ? 1 : s);
    double t = c > 0 ? (b * s + e) / c : 0.0;
    if (t < -1 || t > 1) {
        t = t < -1 ? -1 : 1;
        s = a > 0 ? (b * t - d) / a : 0.0;
        s = s < -1 ? -1 : (s > 1 ? 1 : s);
    }
    double r2 = 0.0;
    for (int k = 0; k < 3; k++) {
        const double x = w[k] + s * u[k] - t * v[k];
        r2 += x * x;
    }
    return r2;
}

/* ---- GJK on the primitives (convex, given by their support points): certified distances and verdicts ----
 *
 * What the closed forms above do not cover (a cylinder against a box or a cylinder, two boxes for clearances) is
 * decided with GJK on the Minkowski difference. Every answer it gives is certified by bounds that hold whatever
 * the simplex bookkeeping did: |v| (v a convex combination of support points, so a point of A - B) is an upper
 * bound of the distance and v.w / |v| (w the support point of A - B towards -v) a lower bound. A distance is
 * returned only when the two agree within the tolerance; "intersecting" only when the origin is strictly inside
 * a tetrahedron of support points. Anything else (touching, degenerate simplex, no convergence) is left to fcl.
 */

typedef struct {
    int kind;
    const double *T;  /* pose, 3x4 row-major (the first 12 entries of a 4x4 row-major pose) */
    double d[3];      /* sphere (r), box (half x, y, z), cylinder (r, half length) */
} Shape;

static void support(const Shape *s, const double *dir, double *out) {
    const double *T = s->T;
    const double l[3] = {T[0] * dir[0] + T[4] * dir[1] + T[8] * dir[2], T[1] * dir[0] + T[5] * dir[1] + T[9] * dir[2],
                         T[2] * dir[0] + T[6] * dir[1] + T[10] * dir[2]};
    double p[3] = {0.0, 0.0, 0.0};
    if (s->kind == SPHERE) {
        const double n = sqrt(dot3(l, l));
        if (n > 0)
            for (int k = 0; k < 3; k++)
                p[k] = l[k] * (s->d[0] / n);
        else
            p[0] = s->d[0];
    } else if (s->kind == BOX) {
        for (int k = 0; k < 3; k++)
            p[k] = l[k] >= 0 ? s->d[k] : -s->d[k];
    } else {
        const double rr = sqrt(l[0] * l[0] + l[1] * l[1]);  /* not hypot: several times slower, no overflow here */
        if (rr > 0) {
            const double scale = s->d[0] / rr;
            p[0] = l[0] * scale;
            p[1] = l[1] * scale;
        }
        p[2] = l[2] >= 0 ? s->d[1] : -s->d[1];
    }
    for (int r = 0; r < 3; r++)
        out[r] = T[4 * r] * p[0] + T[4 * r + 1] * p[1] + T[4 * r + 2] * p[2] + T[4 * r + 3];
}

/* Support point of A - B in direction dir. */
static void support_diff(const Shape *a, const Shape *b, const double *dir, double *out) {
    const double neg[3] = {-dir[0], -dir[1], -dir[2]};
    double pa[3], pb[3];
    support(a, dir, pa);
    support(b, neg, pb);
    for (int k = 0; k < 3; k++)
        out[k] = pa[k] - pb[k];
}

static inline void sub3(const double *a, const double *b, double *c) {
    c[0] = a[0] - b[0]; c[1] = a[1] - b[1]; c[2] = a[2] - b[2];
}

static inline void cross3(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

/* Closest point to the origin on segment W[0]W[1]; keeps the vertices of the feature it lies on. */
static void closest_segment(double W[4][3], int *n, double *v) {
    double e[3];
    sub3(W[1], W[0], e);
    const double ee = dot3(e, e), t = ee > 0 ? -dot3(W[0], e) / ee : 0.0;
    if (t <= 0) {
        *n = 1;
        memcpy(v, W[0], sizeof(double) * 3);
    } else if (t >= 1) {
        *n = 1;
        memcpy(W[0], W[1], sizeof(double) * 3);
        memcpy(v, W[0], sizeof(double) * 3);
    } else {
        for (int k = 0; k < 3; k++)
            v[k] = W[0][k] + t * e[k];
    }
}

/* Closest point to the origin on triangle W[0..2] (Voronoi regions, as in Ericson's Real-Time Collision
 * Detection 5.1.5); keeps the vertices of the feature it lies on. */
static void closest_triangle(double W[4][3], int *n, double *v) {
    const double *a = W[0], *b = W[1], *c = W[2];
    double ab[3], ac[3], ap[3] = {-a[0], -a[1], -a[2]};
    sub3(b, a, ab);
    sub3(c, a, ac);
    const double d1 = dot3(ab, ap), d2 = dot3(ac, ap);
    double keep[3][3];
    if (d1 <= 0 && d2 <= 0) {  /* vertex a */
        *n = 1;
        memcpy(v, a, sizeof keep[0]);
        return;
    }
    const double bp[3] = {-b[0], -b[1], -b[2]};
    const double d3 = dot3(ab, bp), d4 = dot3(ac, bp);
    if (d3 >= 0 && d4 <= d3) {  /* vertex b */
        *n = 1;
        memcpy(W[0], b, sizeof keep[0]);
        memcpy(v, W[0], sizeof keep[0]);
        return;
    }
    const double vc = d1 * d4 - d3 * d2;
    if (vc <= 0 && d1 >= 0 && d3 <= 0) {  /* edge ab */
        const double t = d1 / (d1 - d3);
        for (int k = 0; k < 3; k++)
            v[k] = a[k] + t * ab[k];
        *n = 2;
        return;
    }
    const double cp[3] = {-c[0], -c[1], -c[2]};
    const double d5 = dot3(ab, cp), d6 = dot3(ac, cp);
    if (d6 >= 0 && d5 <= d6) {  /* vertex c */
        *n = 1;
        memcpy(W[0], c, sizeof keep[0]);
        memcpy(v, W[0], sizeof keep[0]);
        return;
    }
    const double vb = d5 * d2 - d1 * d6;
    if (vb <= 0 && d2 >= 0 && d6 <= 0) {  /* edge ac */
        const double t = d2 / (d2 - d6);
        for (int k = 0; k < 3; k++)
            v[k] = a[k] + t * ac[k];
        memcpy(W[1], c, sizeof keep[0]);
        *n = 2;
        return;
    }
    const double va = d3 * d6 - d5 * d4;
    if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {  /* edge bc */
        const double t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        for (int k = 0; k < 3; k++)
            v[k] = b[k] + t * (c[k] - b[k]);
        memcpy(W[0], c, sizeof keep[0]);
        *n = 2;
        return;
    }
    const double den = va + vb + vc;
    if (!(den > 0)) {  /* degenerate (flat) triangle: the closest of its edges */
        double best = INFINITY, bv[3] = {0, 0, 0}, S[4][3];
        int bn = 0;
        double Bs[4][3];
        for (int e = 0; e < 3; e++) {
            int m = 2;
            double u[3];
            memcpy(S[0], W[e], sizeof keep[0]);
            memcpy(S[1], W[(e + 1) % 3], sizeof keep[0]);
            closest_segment(S, &m, u);
            if (dot3(u, u) < best) {
                best = dot3(u, u);
                memcpy(bv, u, sizeof bv);
                memcpy(Bs, S, sizeof Bs);
                bn = m;
            }
        }
        memcpy(W, Bs, sizeof Bs);
        *n = bn;
        memcpy(v, bv, sizeof bv);
        return;
    }
    const double sv = vb / den, sw = vc / den;
    for (int k = 0; k < 3; k++)
        v[k] = a[k] + ab[k] * sv + ac[k] * sw;
    *n = 3;
}

/* Closest point to the origin on tetrahedron W[0..3]: the closest over the faces the origin is outside of.
 * Returns 1 when the origin is strictly inside (by `inside` relative to the face's scale), else 0 (and the
 * reduced simplex and point). A flat tetrahedron is never "inside": its faces are all tried. */
static int closest_tetra(double W[4][3], int *n, double *v) {
    static const int face[4][4] = {{0, 1, 2, 3}, {0, 2, 3, 1}, {0, 3, 1, 2}, {1, 3, 2, 0}};
    double e1[3], e2[3], nrm[3], d[3], po[3];
    sub3(W[1], W[0], e1);
    sub3(W[2], W[0], e2);
    cross3(e1, e2, nrm);
    sub3(W[3], W[0], d);
    const double vol = dot3(nrm, d);
    double scale = 0.0;
    for (int i = 0; i < 4; i++)
        scale = fmax(scale, dot3(W[i], W[i]));
    const int flat = fabs(vol) <= 1e-12 * scale * sqrt(scale);
    int outside_any = 0;
    double best = INFINITY, bv[3] = {0, 0, 0}, Bs[4][3];
    int bn = 0;
    for (int f = 0; f < 4; f++) {
        const double *a = W[face[f][0]], *b = W[face[f][1]], *c = W[face[f][2]], *o = W[face[f][3]];
        sub3(b, a, e1);
        sub3(c, a, e2);
        cross3(e1, e2, nrm);
        sub3(o, a, d);
        po[0] = -a[0]; po[1] = -a[1]; po[2] = -a[2];
        const double so = dot3(nrm, d), sp = dot3(nrm, po);
        const double nn = sqrt(dot3(nrm, nrm));
        /* outside this face: the origin and the opposite vertex on different sides (or a flat tetrahedron),
         * or too close to the face to tell (then it is not "strictly inside" either) */
        const int outside = flat || sp * so <= 0 || fabs(sp) <= 1e-12 * nn * sqrt(scale);
        if (!outside)
            continue;
        outside_any = 1;
        double S[4][3], u[3];
        int m = 3;
        memcpy(S[0], a, sizeof S[0]);
        memcpy(S[1], b, sizeof S[0]);
        memcpy(S[2], c, sizeof S[0]);
        closest_triangle(S, &m, u);
        if (dot3(u, u) < best) {
            best = dot3(u, u);
            memcpy(bv, u, sizeof bv);
            memcpy(Bs, S, sizeof Bs);
            bn = m;
        }
    }
    if (!outside_any)
        return 1;
    memcpy(W, Bs, sizeof Bs);
    *n = bn;
    memcpy(v, bv, sizeof bv);
    return 0;
}

enum { GJK_UNDECIDED = -1, GJK_INTERSECT = 0, GJK_APART = 1 };

/* GJK between a and b. GJK_APART with *dist within `tol` of the distance (certified), or, when `apart_above` is
 * finite, as soon as the lower bound exceeds it (*dist = that lower bound); GJK_INTERSECT when the origin is
 * strictly inside a tetrahedron of support points of A - B (the shapes share an interior point); else
 * GJK_UNDECIDED. */
static int gjk_simplex(const Shape *a, const Shape *b, double tol, double apart_above, double *dist, double W[4][3]) {
    double v[3], w[3];
    int n = 1;
    const double dir0[3] = {a->T[3] - b->T[3], a->T[7] - b->T[7], a->T[11] - b->T[11]};
    const double one[3] = {1.0, 0.0, 0.0};
    support_diff(a, b, dot3(dir0, dir0) > 0 ? dir0 : one, W[0]);
    memcpy(v, W[0], sizeof v);
    double upper = INFINITY, lower = -INFINITY;  /* the best bounds so far */
    double last = INFINITY, restart[3];  /* |v| of the run's last step; the support point towards its best v */
    int restarts = 0;
    for (int iter = 0; iter < 64 * (1 + GJK_RESTARTS); iter++) {
        const double vv = dot3(v, v);
        if (!(vv > 1e-24))  /* touching, or lost: not ours to decide */
            return GJK_UNDECIDED;
        const double vn = sqrt(vv);
        if (!(vn < last)) {  /* no progress (rounding on a flat simplex of points close together) */
            if (restarts == GJK_RESTARTS || !(lower > 0))
                break;  /* the bounds decide, or fcl */
            /* apart and stuck a few nanometres short of the tolerance (a cylinder's rim against a face): a new run
             * from the support point towards the best direction, with the bounds kept (they hold whatever the
             * simplex did) */
            restarts++;
            n = 1;
            memcpy(W[0], restart, sizeof restart);
            memcpy(v, restart, sizeof v);
            last = INFINITY;
            continue;
        }
        last = vn;
        upper = fmin(upper, vn);
        const double neg[3] = {-v[0], -v[1], -v[2]};
        support_diff(a, b, neg, w);
        if (vn <= upper)
            memcpy(restart, w, sizeof w);
        lower = fmax(lower, dot3(v, w) / vn);
        if (lower > apart_above) {
            *dist = lower;
            return GJK_APART;
        }
        if (upper - lower <= tol)
            break;
        memcpy(W[n++], w, sizeof w);
        if (n == 2)
            closest_segment(W, &n, v);
        else if (n == 3)
            closest_triangle(W, &n, v);
        else if (closest_tetra(W, &n, v))
            return GJK_INTERSECT;
    }
    if (upper - lower <= tol && lower > 0) {
        *dist = upper;
        return GJK_APART;
    }
    return GJK_UNDECIDED;
}

static int gjk(const Shape *a, const Shape *b, double tol, double apart_above, double *dist) {
    double W[4][3];
    return gjk_simplex(a, b, tol, apart_above, dist, W);
}

/* EPA: the penetration depth of two overlapping shapes (the distance from the origin to the boundary of A - B),
 * grown from GJK's tetrahedron around the origin. Certified as GJK is: the polytope lies inside A - B, so its
 * nearest face's distance is a lower bound of the depth, and the support value of A - B along any direction an
 * upper bound; the depth is returned when the nearest face's distance and the lowest support value seen agree
 * within `tol`. Returns 1 and *depth, or 0 (no tetrahedron, a degenerate face, out of room or iterations): ask
 * fcl. The faces are kept packed (the last face takes a removed one's slot), so each iteration is one pass over
 * the live faces: which ones the new point sees, and the nearest of the others and the new ones. */
#define EPA_VERTS 132
#define EPA_FACES (2 * EPA_VERTS)

typedef struct {
    int v[3];
    double n[3], d;  /* unit outward normal, distance of the plane from the origin */
} Face;

/* Face through vertices i0, i1, i2 of V (counter-clockwise seen from outside); 0 when degenerate or when the
 * origin is outside its plane (numerically lost). */
static int face_make(double V[][3], int i0, int i1, int i2, Face *f) {
    double e1[3], e2[3], n[3];
    sub3(V[i1], V[i0], e1);
    sub3(V[i2], V[i0], e2);
    cross3(e1, e2, n);
    const double len = sqrt(dot3(n, n));
    if (!(len > 1e-18))
        return 0;
    f->v[0] = i0; f->v[1] = i1; f->v[2] = i2;
    for (int k = 0; k < 3; k++)
        f->n[k] = n[k] / len;
    f->d = dot3(f->n, V[i0]);
    return f->d >= -1e-12;
}

static int epa(const Shape *a, const Shape *b, double W[4][3], double tol, double *depth) {
    double V[EPA_VERTS][3];
    Face F[EPA_FACES];
    int nf = 0, nv = 4, best = -1;
    memcpy(V, W, sizeof(double) * 12);
    static const int tet[4][4] = {{0, 1, 2, 3}, {0, 3, 1, 2}, {0, 2, 3, 1}, {1, 3, 2, 0}};
    for (int f = 0; f < 4; f++) {
        int i0 = tet[f][0], i1 = tet[f][1], i2 = tet[f][2];
        double e1[3], e2[3], n[3], o[3];
        sub3(V[i1], V[i0], e1);
        sub3(V[i2], V[i0], e2);
        cross3(e1, e2, n);
        sub3(V[tet[f][3]], V[i0], o);
        if (dot3(n, o) > 0) {  /* orient outwards: away from the opposite vertex */
            const int t = i1; i1 = i2; i2 = t;
        }
        if (!face_make(V, i0, i1, i2, &F[nf]))
            return 0;
        if (best < 0 || F[nf].d < F[best].d)
            best = nf;
        nf++;
    }
    double upper = INFINITY;
    for (int iter = 0;; iter++) {
        double w[3];
        support_diff(a, b, F[best].n, w);
        upper = fmin(upper, dot3(F[best].n, w));
        if (upper - F[best].d <= tol) {
            *depth = F[best].d > 0 ? F[best].d : 0.0;
            return 1;
        }
        if (nv == EPA_VERTS || iter > EPA_VERTS)
            return 0;
        memcpy(V[nv], w, sizeof w);
        /* remove the faces w sees (the last face takes a removed one's slot); the horizon, their edges not
         * shared by another removed face, gets new faces to w */
        int edges[3 * EPA_FACES][2], ne = 0;
        double nearest = INFINITY;  /* (in a register: F[best].d would be reloaded after every store) */
        best = -1;
        for (int f = 0; f < nf;) {
            const double fd = F[f].d;
            if (dot3(F[f].n, w) - fd <= 1e-12) {  /* w on or behind a face's plane: keep the face */
                if (fd < nearest) {
                    nearest = fd;
                    best = f;
                }
                f++;
                continue;
            }
            for (int e = 0; e < 3; e++) {
                const int u = F[f].v[e], x = F[f].v[(e + 1) % 3];
                int shared = -1;
                for (int k = 0; k < ne; k++)
                    if (edges[k][0] == x && edges[k][1] == u) {
                        shared = k;
                        break;
                    }
                if (shared >= 0) {
                    edges[shared][0] = edges[--ne][0];
                    edges[shared][1] = edges[ne][1];
                } else {
                    edges[ne][0] = u;
                    edges[ne][1] = x;
                    ne++;
                }
            }
            F[f] = F[--nf];  /* not yet looked at: f is looked at again */
        }
        if (ne == 0 || nf + ne > EPA_FACES)
            return 0;
        for (int k = 0; k < ne; k++) {
            if (!face_make(V, edges[k][0], edges[k][1], nv, &F[nf]))
                return 0;
            if (F[nf].d < nearest) {
                nearest = F[nf].d;
                best = nf;
            }
            nf++;
        }
        nv++;
    }
}

/* Signed distance of two shapes by GJK, and EPA when they overlap: NAN when neither certifies an answer. */
static double gjk_epa(const Shape *a, const Shape *b) {
    double W[4][3], d;
    const int g = gjk_simplex(a, b, GJK_TOL, INFINITY, &d, W);
    if (g == GJK_APART)
        return d;
    if (g == GJK_INTERSECT && epa(a, b, W, GJK_TOL, &d))
        return -d;
    return NAN;
}

static void make_shape(Shape *s, int kind, const double *T, const double *dims, double grow) {
    s->kind = kind;
    s->T = T;
    for (int k = 0; k < 3; k++)
        s->d[k] = dims[k] + grow;
}

/* Smallest half dimension of a shape (to know how far it can be shrunk). */
static double thinnest(const Shape *s) {
    if (s->kind == SPHERE)
        return s->d[0];
    if (s->kind == CYLINDER)
        return fmin(s->d[0], s->d[1]);
    return fmin(s->d[0], fmin(s->d[1], s->d[2]));
}

static double signed_distance(const Model *m, const double *poses, Py_ssize_t i, Py_ssize_t j);

/* The status of pair (i, j) at the poses in m->W. With `clearance` (then `poses`: the same poses, P x 4 x 4), a
 * pair that needs GJK gets the signed distance of its un-inflated shapes computed first and stored there (NaN:
 * not certified), and *computed set: the clearance is wanted anyway when the pair overlaps, and it proves most
 * overlaps on its own (see below), sparing the test on the shrunk shapes. */
static int pair_status(const Model *m, Py_ssize_t i, Py_ssize_t j, const double *poses, double *clearance,
                       int *computed) {
    const double *Ti = m->W + 12 * i, *Tj = m->W + 12 * j;
    double ci[3], cj[3];
    centre(Ti, ci);
    centre(Tj, cj);
    const double dx = ci[0] - cj[0], dy = ci[1] - cj[1], dz = ci[2] - cj[2];
    const double reach = m->brad[i] + m->brad[j] + m->eps;
    if (dx * dx + dy * dy + dz * dz > reach * reach)
        return 0;
    int ki = (int)m->kind[i], kj = (int)m->kind[j];
    if (ki > kj) {  /* order the pair: sphere < box < cylinder */
        const double *T = Ti; Ti = Tj; Tj = T;
        Py_ssize_t x = i; i = j; j = x;
        int k = ki; ki = kj; kj = k;
        double c[3];
        memcpy(c, ci, sizeof c); memcpy(ci, cj, sizeof c); memcpy(cj, c, sizeof c);
    }
    const double *di = m->dims + 3 * i, *dj = m->dims + 3 * j;
    const double eps = m->eps;
    if (ki == SPHERE) {
        double p[3];
        if (kj == SPHERE)
            return classify(sqrt(dx * dx + dy * dy + dz * dz) - di[0] - dj[0], eps);
        to_local(Tj, ci, p);
        if (kj == BOX)
            return classify(point_box(p, dj) - di[0], eps);
        return classify(point_cylinder(p, dj[0], dj[1]) - di[0], eps);
    }
    if (ki == BOX && kj == BOX)
        return obb_obb(Ti, di, Tj, dj, eps);
    /* a cylinder against a box or a cylinder: its bounding box, and for two cylinders their capsules */
    const double hi[3] = {ki == BOX ? di[0] : di[0], ki == BOX ? di[1] : di[0], ki == BOX ? di[2] : di[1]};
    const double hj[3] = {dj[0], dj[0], dj[1]};
    if (obb_obb(Ti, hi, Tj, hj, eps) == 0)
        return 0;
    if (ki == CYLINDER) {
        double u[3], v[3];
        axis(Ti, 2, u);
        axis(Tj, 2, v);
        for (int k = 0; k < 3; k++) {
            u[k] *= di[1];
            v[k] *= dj[1];
        }
        const double r = di[0] + dj[0] + eps;
        if (segment_segment2(ci, u, cj, v) > r * r)
            return 0;
    }
    Shape a, b;
    double d;
    if (clearance != NULL) {
        /* The clearance first (wanted anyway when the pair overlaps; pairs with a sphere never get here): one GJK on
         * the un-inflated shapes decides most pairs. An inflated primitive lies within its un-inflated one grown by
         * a ball of radius sqrt(3) padmax (a box's corner moves that far, a cylinder's rim sqrt(2) pad), so
         * un-inflated shapes further apart than sqrt(3) (padmax_i + padmax_j) + eps leave the inflated ones apart
         * by more than eps. And it contains the un-inflated one grown by pad, so, shrunk by eps, the one grown by
         * pad - eps: un-inflated shapes closer than pad_i + pad_j - 2 eps (certified within GJK_TOL) make the
         * shrunk inflated ones share an interior point, which is what the test below proves. */
        const double far = 1.7320508075688774 * (m->padmax[i] + m->padmax[j]) + eps + GJK_TOL;
        double W[4][3];
        make_shape(&a, ki, Ti, m->raw + 3 * i, 0.0);
        make_shape(&b, kj, Tj, m->raw + 3 * j, 0.0);
        const int g = gjk_simplex(&a, &b, GJK_TOL, far, &d, W);
        if (g == GJK_APART && d > far)  /* a lower bound past `far`, or the distance within GJK_TOL */
            return 0;
        *computed = 1;
        *clearance = g == GJK_APART ? d : (g == GJK_INTERSECT && epa(&a, &b, W, GJK_TOL, &d) ? -d : NAN);
        if (*clearance + GJK_TOL < m->pad[i] + m->pad[j] - 2 * eps)
            return 2;
    }
    /* GJK on the shapes themselves: apart when the certified lower bound of their distance exceeds eps;
     * overlapping by more than eps when the shapes shrunk by eps on every side still share an interior point */
    make_shape(&a, ki, Ti, di, 0.0);
    make_shape(&b, kj, Tj, dj, 0.0);
    if (gjk(&a, &b, GJK_TOL, eps, &d) == GJK_APART && d - GJK_TOL > eps)
        return 0;
    if (thinnest(&a) > 2 * eps && thinnest(&b) > 2 * eps) {
        make_shape(&a, ki, Ti, di, -eps);
        make_shape(&b, kj, Tj, dj, -eps);
        if (gjk(&a, &b, GJK_TOL, 0.0, &d) == GJK_INTERSECT)
            return 2;
    }
    return 1;
}

/* Signed distance (m) between primitives i and j, un-inflated, posed by `poses` (P x 4 x 4): > 0 the gap, < 0
 * the overlap depth. Exact closed forms for every pair with a sphere; GJK (within GJK_TOL) for the others when
 * they are apart; NAN when this code cannot tell (overlapping or touching shapes without a sphere): ask fcl. */
static double signed_distance(const Model *m, const double *poses, Py_ssize_t i, Py_ssize_t j) {
    int ki = (int)m->kind[i], kj = (int)m->kind[j];
    if (ki > kj) {
        Py_ssize_t x = i; i = j; j = x;
        int k = ki; ki = kj; kj = k;
    }
    const double *Ti = poses + 16 * i, *Tj = poses + 16 * j, *di = m->raw + 3 * i, *dj = m->raw + 3 * j;
    double ci[3], p[3];
    centre(Ti, ci);
    if (ki == SPHERE) {
        if (kj == SPHERE) {
            double cj[3];
            centre(Tj, cj);
            return sqrt((ci[0] - cj[0]) * (ci[0] - cj[0]) + (ci[1] - cj[1]) * (ci[1] - cj[1])
                        + (ci[2] - cj[2]) * (ci[2] - cj[2])) - di[0] - dj[0];
        }
        to_local(Tj, ci, p);
        return (kj == BOX ? point_box(p, dj) : point_cylinder(p, dj[0], dj[1])) - di[0];
    }
    Shape a, b;
    make_shape(&a, ki, Ti, di, 0.0);
    make_shape(&b, kj, Tj, dj, 0.0);
    return gjk_epa(&a, &b);
}

/* Joint frames and primitive poses of configuration q into m->T, m->W. */
static void place(Model *m, const double *q) {
    const Py_ssize_t n = m->n;
    double *root = m->T + 12 * n;
    memset(root, 0, 12 * sizeof(double));
    root[0] = root[5] = root[10] = 1.0;
    for (Py_ssize_t k = 0; k < n; k++) {
        const Py_ssize_t i = m->order[k];
        const double s = sin(q[i]), c1 = 1.0 - cos(q[i]);
        const double *A0 = m->A + 36 * i, *A1 = A0 + 12, *A2 = A0 + 24;
        double local[12];
        for (int e = 0; e < 12; e++)
            local[e] = A0[e] + s * A1[e] + c1 * A2[e];
        compose(m->T + 12 * m->parent[i], local, m->T + 12 * i);
    }
    for (Py_ssize_t p = 0; p < m->P; p++)
        compose(m->T + 12 * m->owner[p], m->offset + 12 * p, m->W + 12 * p);
}

/* screen(handle, q, poses_out, stop_at_sure) -> list of pair indices not proven apart, in pair order; a pair
 * proven to overlap is given as -1 - index. poses_out (P x 4 x 4 doubles, writable) receives the primitive
 * poses. With stop_at_sure, the list ends at the first proven overlap (a yes/no question). */
static int fill_poses(Model *m, Py_buffer *qb, Py_buffer *pb, const char *who);

static PyObject *screen(PyObject *self, PyObject *args) {
    PyObject *cap;
    Py_buffer qb, pb;
    int stop = 0;
    if (!PyArg_ParseTuple(args, "Oy*w*|p", &cap, &qb, &pb, &stop))
        return NULL;
    PyObject *out = NULL;
    Model *m = PyCapsule_GetPointer(cap, "mds_collfast.Model");
    if (m == NULL)
        goto done;
    if (fill_poses(m, &qb, &pb, "screen") < 0)
        goto done;
    out = PyList_New(0);
    if (out == NULL)
        goto done;
    for (Py_ssize_t k = 0; k < m->M; k++) {
        const int status = pair_status(m, m->I[k], m->J[k], NULL, NULL, NULL);
        if (status == 0)
            continue;
        PyObject *v = PyLong_FromSsize_t(status == 2 ? -1 - k : k);
        if (v == NULL || PyList_Append(out, v) < 0) {
            Py_XDECREF(v);
            Py_CLEAR(out);
            goto done;
        }
        Py_DECREF(v);
        if (stop && status == 2)
            break;
    }
done:
    PyBuffer_Release(&qb);
    PyBuffer_Release(&pb);
    return out;
}

/* poses(handle, q, poses_out): the primitive poses of configuration q (P x 4 x 4 doubles), no pair test. */
static int fill_poses(Model *m, Py_buffer *qb, Py_buffer *pb, const char *who) {
    if (qb->len != m->n * (Py_ssize_t)sizeof(double) || pb->len != m->P * 16 * (Py_ssize_t)sizeof(double)) {
        PyErr_Format(PyExc_ValueError, "_collfast.%s: q needs %zd doubles and poses %zd, got %zd and %zd bytes", who,
                     m->n, m->P * 16, qb->len, pb->len);
        return -1;
    }
    place(m, (const double *)qb->buf);
    double *poses = pb->buf;
    for (Py_ssize_t p = 0; p < m->P; p++) {
        memcpy(poses + 16 * p, m->W + 12 * p, 12 * sizeof(double));
        poses[16 * p + 12] = poses[16 * p + 13] = poses[16 * p + 14] = 0.0;
        poses[16 * p + 15] = 1.0;
    }
    return 0;
}

static PyObject *poses(PyObject *self, PyObject *args) {
    PyObject *cap;
    Py_buffer qb, pb;
    if (!PyArg_ParseTuple(args, "Oy*w*", &cap, &qb, &pb))
        return NULL;
    Model *m = PyCapsule_GetPointer(cap, "mds_collfast.Model");
    const int ok = m != NULL && fill_poses(m, &qb, &pb, "poses") == 0;
    PyBuffer_Release(&qb);
    PyBuffer_Release(&pb);
    if (!ok)
        return NULL;
    Py_RETURN_NONE;
}

/* distance(handle, poses, i, j) -> signed distance of primitives i, j (un-inflated), NaN: ask fcl. */
static PyObject *distance(PyObject *self, PyObject *args) {
    PyObject *cap;
    Py_buffer pb;
    Py_ssize_t i, j;
    if (!PyArg_ParseTuple(args, "Oy*nn", &cap, &pb, &i, &j))
        return NULL;
    PyObject *out = NULL;
    Model *m = PyCapsule_GetPointer(cap, "mds_collfast.Model");
    if (m == NULL)
        goto done;
    if (pb.len != m->P * 16 * (Py_ssize_t)sizeof(double) || i < 0 || i >= m->P || j < 0 || j >= m->P) {
        PyErr_Format(PyExc_ValueError, "_collfast.distance: poses need %zd doubles and 0 <= i, j < %zd", m->P * 16,
                     m->P);
        goto done;
    }
    out = PyFloat_FromDouble(signed_distance(m, (const double *)pb.buf, i, j));
done:
    PyBuffer_Release(&pb);
    return out;
}

/* contacts(handle, contact_class, fields, result_class, free): what check_many and check_one build their answers
 * from: an instance of contact_class per contact whose __dict__ is a copy of fields[pair] (a tuple of one dict per
 * pair) with "clearance" set, and an instance of result_class whose __dict__ is {"contacts": (contact, ...)}, as
 * object.__new__ and object.__setattr__(c, "__dict__", ...) would make them (a frozen dataclass's __init__ costs
 * ~0.9 us a contact, a third of the pair list's tail on many-contact configurations); `free` when every pair is
 * apart. */
static PyObject *contacts(PyObject *self, PyObject *args) {
    PyObject *cap, *cls, *fields, *result, *free;
    if (!PyArg_ParseTuple(args, "OO!O!O!O", &cap, &PyType_Type, &cls, &PyTuple_Type, &fields, &PyType_Type, &result,
                          &free))
        return NULL;
    Model *m = PyCapsule_GetPointer(cap, "mds_collfast.Model");
    if (m == NULL)
        return NULL;
    if (PyTuple_GET_SIZE(fields) != m->M) {
        PyErr_Format(PyExc_ValueError, "_collfast.contacts: fields needs one dict per pair (%zd), got %zd", m->M,
                     PyTuple_GET_SIZE(fields));
        return NULL;
    }
    for (Py_ssize_t k = 0; k < m->M; k++)
        if (!PyDict_Check(PyTuple_GET_ITEM(fields, k))) {
            PyErr_SetString(PyExc_TypeError, "_collfast.contacts: fields must be dicts");
            return NULL;
        }
    Py_INCREF(cls);
    Py_INCREF(fields);
    Py_INCREF(result);
    Py_INCREF(free);
    Py_XSETREF(m->contact, cls);
    Py_XSETREF(m->fields, fields);
    Py_XSETREF(m->result, result);
    Py_XSETREF(m->free, free);
    Py_RETURN_NONE;
}

static PyObject *empty_args, *dict_name, *clearance_name, *contacts_name;

/* An instance of cls whose __dict__ is `values` (a reference taken). */
static PyObject *instance(PyObject *cls, PyObject *values) {
    if (values == NULL)
        return NULL;
    PyObject *out = PyBaseObject_Type.tp_new((PyTypeObject *)cls, empty_args, NULL);
    if (out != NULL && PyObject_GenericSetAttr(out, dict_name, values) < 0)
        Py_CLEAR(out);
    Py_DECREF(values);
    return out;
}

static PyObject *make_contact(const Model *m, Py_ssize_t k, double d) {
    PyObject *values = PyDict_Copy(PyTuple_GET_ITEM(m->fields, k)), *clearance = PyFloat_FromDouble(d);
    if (values == NULL || clearance == NULL || PyDict_SetItem(values, clearance_name, clearance) < 0) {
        Py_XDECREF(values);
        Py_XDECREF(clearance);
        return NULL;
    }
    Py_DECREF(clearance);
    return instance(m->contact, values);
}

/* The answer for configuration q (m->n doubles): m->free, a result_class instance with the contacts, or Py_False
 * (ask fcl); a new reference, NULL on error. */
static PyObject *answer(Model *m, const double *q) {
    PyObject *stack[64], **found = stack;  /* the contacts so far (on the heap past 64) */
    Py_ssize_t nfound = 0, room = 64;
    double *poses = m->poses;
    place(m, q);
    for (Py_ssize_t p = 0; p < m->P; p++) {
        memcpy(poses + 16 * p, m->W + 12 * p, 12 * sizeof(double));
        poses[16 * p + 12] = poses[16 * p + 13] = poses[16 * p + 14] = 0.0;
        poses[16 * p + 15] = 1.0;
    }
    PyObject *out = NULL;
    for (Py_ssize_t k = 0; k < m->M; k++) {
        double d = NAN;
        int computed = 0;
        const int status = pair_status(m, m->I[k], m->J[k], poses, &d, &computed);
        if (status == 0)
            continue;
        if (status == 2 && !computed)
            d = signed_distance(m, poses, m->I[k], m->J[k]);
        if (status != 2 || d != d) {  /* fcl's: the rest would be thrown away */
            out = Py_False;
            Py_INCREF(out);
            goto done;
        }
        if (nfound == room) {
            PyObject **more = PyMem_Malloc(2 * room * sizeof(PyObject *));
            if (more == NULL) {
                PyErr_NoMemory();
                goto done;
            }
            memcpy(more, found, nfound * sizeof(PyObject *));
            if (found != stack)
                PyMem_Free(found);
            found = more;
            room *= 2;
        }
        if ((found[nfound] = make_contact(m, k, d)) == NULL)
            goto done;
        nfound++;
    }
    if (nfound == 0) {
        out = m->free;
        Py_INCREF(out);
        goto done;
    }
    PyObject *tuple = PyTuple_New(nfound), *values = PyDict_New();
    if (tuple == NULL || values == NULL || PyDict_SetItem(values, contacts_name, tuple) < 0) {
        Py_XDECREF(tuple);
        Py_XDECREF(values);
        goto done;
    }
    for (Py_ssize_t k = 0; k < nfound; k++)
        PyTuple_SET_ITEM(tuple, k, found[k]);  /* the tuple takes the references */
    nfound = 0;
    Py_DECREF(tuple);
    out = instance(m->result, values);
done:
    for (Py_ssize_t k = 0; k < nfound; k++)
        Py_DECREF(found[k]);
    if (found != stack)
        PyMem_Free(found);
    return out;
}

/* The model of a handle, with contacts() done. */
static Model *ready(PyObject *cap, const char *who) {
    Model *m = PyCapsule_GetPointer(cap, "mds_collfast.Model");
    if (m != NULL && m->contact == NULL) {
        PyErr_Format(PyExc_RuntimeError, "_collfast.%s: call contacts() first", who);
        return NULL;
    }
    return m;
}

/* check_many(handle, Q) -> per row of Q (K x n doubles, C order) its answer: the `free` result when every pair is
 * proven apart; a result with the contacts (see contacts()), in pair order, when every pair not proven apart is
 * proven overlapping by more than eps and has a certified clearance; else False (an undecided pair or an
 * uncertified clearance: ask fcl). One call for all the configurations of a gate frame, and no Python work per
 * configuration or pair. */
static PyObject *check_many(PyObject *self, PyObject *args) {
    PyObject *cap;
    Py_buffer qb;
    if (!PyArg_ParseTuple(args, "Oy*", &cap, &qb))
        return NULL;
    PyObject *out = NULL;
    Model *m = ready(cap, "check_many");
    if (m == NULL)
        goto done;
    const Py_ssize_t row = m->n * (Py_ssize_t)sizeof(double);
    if (row == 0 || qb.len % row != 0) {
        PyErr_Format(PyExc_ValueError, "_collfast.check_many: Q needs rows of %zd doubles, got %zd bytes", m->n, qb.len);
        goto done;
    }
    const Py_ssize_t K = qb.len / row;
    out = PyList_New(K);
    for (Py_ssize_t r = 0; out != NULL && r < K; r++) {
        PyObject *verdict = answer(m, (const double *)qb.buf + r * m->n);
        if (verdict == NULL)
            Py_CLEAR(out);
        else
            PyList_SET_ITEM(out, r, verdict);
    }
done:
    PyBuffer_Release(&qb);
    return out;
}

/* check_one(handle, q) -> the answer for one configuration (as check_many's), or NotImplemented when q is not a
 * C-contiguous buffer of n doubles (the caller converts it). Without numpy's conversions: the pair list of one
 * configuration is what the gate's per-frame time and the benchmark's pair-list rows are made of. */
static PyObject *check_one(PyObject *self, PyObject *args) {
    PyObject *cap, *q;
    if (!PyArg_ParseTuple(args, "OO", &cap, &q))
        return NULL;
    Model *m = ready(cap, "check_one");
    if (m == NULL)
        return NULL;
    Py_buffer qb;
    if (!PyObject_CheckBuffer(q) || PyObject_GetBuffer(q, &qb, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyErr_Clear();
        Py_RETURN_NOTIMPLEMENTED;
    }
    const char *f = qb.format;
    if (f != NULL && (*f == '<' || *f == '=' || *f == '@'))
        f++;
    if (f == NULL || strcmp(f, "d") != 0 || qb.itemsize != sizeof(double) || qb.len != m->n * (Py_ssize_t)sizeof(double)) {
        PyBuffer_Release(&qb);
        Py_RETURN_NOTIMPLEMENTED;
    }
    PyObject *out = answer(m, (const double *)qb.buf);
    PyBuffer_Release(&qb);
    return out;
}

static PyMethodDef methods[] = {
    {"build", build, METH_VARARGS,
     "build(n, P, M, eps, A, parent, order, owner, offset, kind, dims, raw, brad, I, J)"},
    {"screen", screen, METH_VARARGS, "screen(handle, q, poses_out, stop_at_sure=False) -> [pair or -1 - pair]"},
    {"poses", poses, METH_VARARGS, "poses(handle, q, poses_out): primitive poses only"},
    {"contacts", contacts, METH_VARARGS,
     "contacts(handle, contact_class, fields, result_class, free): what check_many's answers are made of"},
    {"check_many", check_many, METH_VARARGS, "check_many(handle, Q) -> [a result, or False: ask fcl]"},
    {"check_one", check_one, METH_VARARGS, "check_one(handle, q) -> a result, False (ask fcl) or NotImplemented"},
    {"distance", distance, METH_VARARGS, "distance(handle, poses, i, j) -> signed distance (un-inflated), NaN: ask fcl"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moduledef = {PyModuleDef_HEAD_INIT, "_collfast",
                                       "C screen of the collision gate (see _collfast.c)", -1, methods};

PyMODINIT_FUNC PyInit__collfast(void) {
    if ((empty_args = PyTuple_New(0)) == NULL || (dict_name = PyUnicode_InternFromString("__dict__")) == NULL
        || (clearance_name = PyUnicode_InternFromString("clearance")) == NULL
        || (contacts_name = PyUnicode_InternFromString("contacts")) == NULL)
        return NULL;
    return PyModule_Create(&moduledef);
}
