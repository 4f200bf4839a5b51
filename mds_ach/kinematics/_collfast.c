/* The collision gate's per-configuration screen, in C: joint frames, primitive poses and a per-pair test on the
 * inflated primitives that is exact where the geometry is simple (sphere-sphere, sphere-box, sphere-cylinder,
 * box-box by the separating-axis test) and conservative elsewhere (anything with a box or cylinder against a
 * cylinder: separated only when the bounding boxes, or the cylinders' capsules, are).
 *
 * Why C: the numpy path costs ~100 us per configuration, nearly all of it per-call overhead of small arrays
 * (FK level by level, the broad phase); the same arithmetic here takes ~2 us. python-fcl stays the judge of every
 * pair this screen cannot decide, and computes the clearances, so answers are those of python-fcl. Optional:
 * without a compiler, mds_ach.kinematics.collision runs the numpy path (same answers, slower).
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
    double *brad;       /* P: bounding radius about the centre */
    int64_t *I, *J;     /* M pairs */
    double *T;          /* (n + 1) * 12 work: joint frames */
    double *W;          /* P * 12 work: primitive poses */
} Model;

static void model_free(Model *m) {
    if (m == NULL)
        return;
    PyMem_Free(m->A); PyMem_Free(m->parent); PyMem_Free(m->order); PyMem_Free(m->owner);
    PyMem_Free(m->offset); PyMem_Free(m->kind); PyMem_Free(m->dims); PyMem_Free(m->brad);
    PyMem_Free(m->I); PyMem_Free(m->J); PyMem_Free(m->T); PyMem_Free(m->W);
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

/* build(n, P, M, eps, A, parent, order, owner, offset, kind, dims, brad, I, J) -> handle */
static PyObject *build(PyObject *self, PyObject *args) {
    Py_ssize_t n, P, M;
    double eps;
    PyObject *A, *parent, *order, *owner, *offset, *kind, *dims, *brad, *I, *J;
    if (!PyArg_ParseTuple(args, "nnndOOOOOOOOOO", &n, &P, &M, &eps, &A, &parent, &order, &owner, &offset, &kind,
                          &dims, &brad, &I, &J))
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
    if (m->T == NULL || m->W == NULL) {
        model_free(m);
        return PyErr_NoMemory();
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

static int pair_status(const Model *m, Py_ssize_t i, Py_ssize_t j) {
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
    return 1;
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
    if (qb.len != m->n * (Py_ssize_t)sizeof(double) || pb.len != m->P * 16 * (Py_ssize_t)sizeof(double)) {
        PyErr_Format(PyExc_ValueError, "_collfast.screen: q needs %zd doubles and poses %zd, got %zd and %zd bytes",
                     m->n, m->P * 16, qb.len, pb.len);
        goto done;
    }
    place(m, (const double *)qb.buf);
    double *poses = pb.buf;
    for (Py_ssize_t p = 0; p < m->P; p++) {
        memcpy(poses + 16 * p, m->W + 12 * p, 12 * sizeof(double));
        poses[16 * p + 12] = poses[16 * p + 13] = poses[16 * p + 14] = 0.0;
        poses[16 * p + 15] = 1.0;
    }
    out = PyList_New(0);
    if (out == NULL)
        goto done;
    for (Py_ssize_t k = 0; k < m->M; k++) {
        const int status = pair_status(m, m->I[k], m->J[k]);
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

static PyMethodDef methods[] = {
    {"build", build, METH_VARARGS, "build(n, P, M, eps, A, parent, order, owner, offset, kind, dims, brad, I, J)"},
    {"screen", screen, METH_VARARGS, "screen(handle, q, poses_out, stop_at_sure=False) -> [pair or -1 - pair]"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moduledef = {PyModuleDef_HEAD_INIT, "_collfast",
                                       "C screen of the collision gate (see _collfast.c)", -1, methods};

PyMODINIT_FUNC PyInit__collfast(void) { return PyModule_Create(&moduledef); }
