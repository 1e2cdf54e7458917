/*
 * slam.graph.accel._kernels: the per-edge loops of slam.graph.accel.host in C (optional, built by setup.py).
 *
 * Why: on the CPU an optimiser iteration in numpy is ~150 array calls whatever the graph's size; on a
 * 9-pose graph (tinyGrid3D) their 1-2 us of dispatch each *is* the run time (3.5x GTSAM's). These
 * functions do the same work in one call each, edge by edge, without temporaries:
 *
 *   residuals(P, ii, jj, zt, zq, L, r, theta2, c, s) -> chi2
 *   linearize(r, theta2, c, neg_adz_t, L, w, rows, dims, F)
 *   retract(P, xi, out)
 *
 * and the setup, assembly and finish of a call: unit_poses, information_factors, measurement_terms,
 * assemble_dense, relocate; and for the sparse Cholesky (slam.graph.cholesky) the small supernodes:
 *
 *   factor_group(buf, offset, B, p, m, upd) -> info,  solve_group(buf, offset, B, p, m, col0, rows, y, fwd)
 *
 * The math is line for line that of slam/graph/accel/host.py and of the torch reference slam/graph/fused.py (same notation, same closed forms, same series
 * below the same angles, set by set_constants() from slam.graph.fused at import); the tests compare
 * them to round-off. Arrays are C-contiguous, aligned, native-endian buffers (float64; int64 indices,
 * int32 update positions) whose sizes are checked here: a wrong size or format, or an index out of
 * range, raises ValueError and nothing is read or written out of bounds. Where a loop runs without the
 * GIL (residuals, linearize, retract) each index is read once and that copy is checked (an index array
 * may change in another thread, or alias an output); factor_group and solve_group keep the GIL and
 * refuse index arrays that share memory with the array they write. Other outputs that alias inputs give
 * unspecified values, never an out-of-bounds access.
 *
 * ABI: the version of this set of functions; slam.graph.accel._compiled refuses a build of another version
 * (an editable install does not rebuild the extension when this file changes).
 * No numpy headers: only the buffer protocol.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* thresholds and series (slam.graph.fused._SMALL / _SMALL_Q / _Q_SERIES for float64) */
static double SMALL2 = 1e-8;   /* _SMALL^2: below it the series of the logarithm and of exp's b */
static double SMALL_Q2 = 1e-4; /* _SMALL_Q^2: below it the series of Barfoot's Q coefficients */
static double QS[3][3] = {{1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0},
                          {-1.0 / 120.0, -1.0 / 720.0, -1.0 / 2520.0},
                          {1.0 / 5040.0, 1.0 / 40320.0, 1.0 / 120960.0}};

/* -- buffers ------------------------------------------------------------------------------------ */
typedef struct {
    Py_buffer view;
    int held;
} Buf;

static void release(Buf *b, int n) {
    for (int i = 0; i < n; i++)
        if (b[i].held) PyBuffer_Release(&b[i].view);
}

/* Get a C-contiguous, aligned, native-endian buffer of `count` items of `kind`: 'd' float64, 'q' int64,
 * 'i' int32. count < 0: any number (the caller checks the size). */
static int get_buf(PyObject *obj, Buf *b, const char *name, char kind, Py_ssize_t count, int writable) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, &b->view, flags) < 0) {
        PyErr_Format(PyExc_ValueError, "%s: expected a C-contiguous%s array", name, writable ? " writable" : "");
        return -1;
    }
    b->held = 1;
    const char *f = b->view.format ? b->view.format : "B";
#if PY_BIG_ENDIAN
    if (*f == '@' || *f == '=' || *f == '>' || *f == '!') f++;
#else
    if (*f == '@' || *f == '=' || *f == '<') f++;
#endif
    Py_ssize_t isz = kind == 'i' ? 4 : 8;
    int fmt = kind == 'd' ? f[0] == 'd' : (kind == 'q' ? (f[0] == 'q' || f[0] == 'l') : (f[0] == 'i' || f[0] == 'l'));
    int ok = b->view.itemsize == isz && f[0] != '\0' && f[1] == '\0' && fmt;
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "%s: expected %s, got format '%s' with %zd-byte items", name,
                     kind == 'd' ? "float64" : (kind == 'q' ? "int64" : "int32"),
                     b->view.format ? b->view.format : "B", b->view.itemsize);
        return -1;
    }
    if (b->view.len > 0 && (uintptr_t)b->view.buf % (uintptr_t)isz != 0) {
        PyErr_Format(PyExc_ValueError, "%s: expected an %zd-byte aligned array", name, isz);
        return -1;
    }
    if (count >= 0 && b->view.len != count * isz) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd values, got %zd", name, count, b->view.len / isz);
        return -1;
    }
    return 0;
}

static Py_ssize_t nvals(Buf *b) { return b->view.len / b->view.itemsize; }

/* A read-only float64 buffer of rows of `width` values (shape written in `shape`, e.g. "(N, 7)"); returns
 * the number of rows, or -1 with an exception set. */
static Py_ssize_t get_rows(PyObject *obj, Buf *b, const char *name, Py_ssize_t width, const char *shape) {
    if (get_buf(obj, b, name, 'd', -1, 0) < 0) return -1;
    Py_ssize_t n = nvals(b) / width;
    if (n * width != nvals(b)) {
        PyErr_Format(PyExc_ValueError, "%s: expected %s values, got %zd", name, shape, nvals(b));
        return -1;
    }
    return n;
}

/* -- geometry (slam/graph/host.py: qmul, qmul_conj, rotmat, cross) ------------------------------------ */
static inline void qmul(const double *a, const double *b, double *o) { /* a b, [x, y, z, w] */
    double x = a[3] * b[0] + b[3] * a[0] + a[1] * b[2] - a[2] * b[1];
    double y = a[3] * b[1] + b[3] * a[1] + a[2] * b[0] - a[0] * b[2];
    double z = a[3] * b[2] + b[3] * a[2] + a[0] * b[1] - a[1] * b[0];
    double w = a[3] * b[3] - (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]);
    o[0] = x, o[1] = y, o[2] = z, o[3] = w;
}

static inline void qmul_conj(const double *a, const double *b, double *o) { /* a b^* */
    double x = b[3] * a[0] - a[3] * b[0] - (a[1] * b[2] - a[2] * b[1]);
    double y = b[3] * a[1] - a[3] * b[1] - (a[2] * b[0] - a[0] * b[2]);
    double z = b[3] * a[2] - a[3] * b[2] - (a[0] * b[1] - a[1] * b[0]);
    double w = a[3] * b[3] + (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]);
    o[0] = x, o[1] = y, o[2] = z, o[3] = w;
}

/* R(q) v with the homogeneous form |q|^2 R(q / |q|) of the matrix (host.rotmat's table) */
static inline void rotate(const double *q, const double *v, double *o) {
    double x = q[0], y = q[1], z = q[2], w = q[3];
    double R00 = w * w + x * x - y * y - z * z, R11 = w * w - x * x + y * y - z * z,
           R22 = w * w - x * x - y * y + z * z;
    double R01 = 2.0 * (x * y - w * z), R10 = 2.0 * (x * y + w * z);
    double R02 = 2.0 * (x * z + w * y), R20 = 2.0 * (x * z - w * y);
    double R12 = 2.0 * (y * z - w * x), R21 = 2.0 * (y * z + w * x);
    double a = v[0], b = v[1], c = v[2];
    o[0] = R00 * a + R01 * b + R02 * c;
    o[1] = R10 * a + R11 * b + R12 * c;
    o[2] = R20 * a + R21 * b + R22 * c;
}

static inline void cross(const double *a, const double *b, double *o) {
    double x = a[1] * b[2] - a[2] * b[1], y = a[2] * b[0] - a[0] * b[2], z = a[0] * b[1] - a[1] * b[0];
    o[0] = x, o[1] = y, o[2] = z;
}

/* r = Log(z^-1 T_i^-1 T_j) and (theta^2, c) of one edge (host._residuals) */
static void residual(const double *Pi, const double *Pj, const double *zt, const double *zq, double *r,
                     double *theta2_out, double *c_out) {
    double a[4], q[4], d[3], t[3];
    qmul_conj(zq, Pi + 3, a);
    d[0] = Pj[0] - Pi[0], d[1] = Pj[1] - Pi[1], d[2] = Pj[2] - Pi[2];
    rotate(a, d, t);
    t[0] += zt[0], t[1] += zt[1], t[2] += zt[2];
    qmul(a, Pj + 3, q);
    double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
    double aw = fabs(q[3]);
    double h = atan2(n, aw);
    double theta2 = 4.0 * h * h;
    double ns = n > DBL_MIN ? n : DBL_MIN;
    double k = copysign(2.0, q[3]) * h / ns; /* sign chosen so that the angle is <= pi */
    double phi[3] = {k * q[0], k * q[1], k * q[2]};
    double c = theta2 < SMALL2 ? 1.0 / 12.0 + theta2 / 720.0 : (1.0 - h * aw / ns) / theta2;
    /* rho = J_l^-1(phi) t = t - phi x t / 2 + c (phi (phi . t) - theta^2 t) */
    double pxt[3];
    cross(phi, t, pxt);
    double pt = phi[0] * t[0] + phi[1] * t[1] + phi[2] * t[2];
    for (int i = 0; i < 3; i++) {
        r[i] = t[i] - 0.5 * pxt[i] + c * (phi[i] * pt - theta2 * t[i]);
        r[3 + i] = phi[i];
    }
    *theta2_out = theta2;
    *c_out = c;
}

/* (c1, c2, c3) of Barfoot's Q (host._q_coefficients) */
static inline void q_coefficients(double theta2, double *c1, double *c2, double *c3) {
    if (theta2 < SMALL_Q2) {
        *c1 = QS[0][0] + theta2 * (QS[1][0] + theta2 * QS[2][0]);
        *c2 = QS[0][1] + theta2 * (QS[1][1] + theta2 * QS[2][1]);
        *c3 = QS[0][2] + theta2 * (QS[1][2] + theta2 * QS[2][2]);
        return;
    }
    double t = sqrt(theta2), sn = sin(t), sh = sin(0.5 * t), t3 = theta2 * t;
    *c1 = (t - sn) / t3;
    *c2 = (theta2 - 4.0 * sh * sh) / (2.0 * theta2 * theta2);
    *c3 = (2.0 * t - 3.0 * sn + t * cos(t)) / (2.0 * t3 * theta2);
}

static inline void hat(const double *p, double H[3][3]) {
    H[0][0] = 0.0, H[0][1] = -p[2], H[0][2] = p[1];
    H[1][0] = p[2], H[1][1] = 0.0, H[1][2] = -p[0];
    H[2][0] = -p[1], H[2][1] = p[0], H[2][2] = 0.0;
}

/* rows [J_i^T; J_j^T; r^T] (13, 6) of one edge (host._jacobians_t) */
static void jacobians_t(const double *r, double theta2, double c, const double *nadz, double JT[13][6]) {
    const double *rho = r, *phi = r + 3;
    double A[3][3], M[3][3], hp[3][3], hv[3][3], AM[3][3], AMA[3][3];
    hat(phi, hp);
    /* A = J_l^-1(phi) = (1 - c t^2) I - hat(phi) / 2 + c phi phi^T */
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) A[i][j] = (i == j ? 1.0 - c * theta2 : 0.0) + c * phi[i] * phi[j] - 0.5 * hp[i][j];
    double c1, c2, c3;
    q_coefficients(theta2, &c1, &c2, &c3);
    double s = phi[0] * rho[0] + phi[1] * rho[1] + phi[2] * rho[2];
    double v[3];
    for (int i = 0; i < 3; i++) v[i] = (0.5 - c2 * theta2) * rho[i] + ((2.0 * c2 - c1) * s) * phi[i];
    hat(v, hv);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            M[i][j] = c1 * (rho[i] * phi[j] + phi[i] * rho[j]) - (2.0 * c3 * s) * phi[i] * phi[j] +
                      (i == j ? 2.0 * s * (c3 * theta2 - c1) : 0.0) + hv[i][j];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) AM[i][j] = A[i][0] * M[0][j] + A[i][1] * M[1][j] + A[i][2] * M[2][j];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) AMA[i][j] = AM[i][0] * A[0][j] + AM[i][1] * A[1][j] + AM[i][2] * A[2][j];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            JT[6 + i][j] = A[i][j];
            JT[6 + i][3 + j] = 0.0;
            JT[9 + i][j] = -AMA[i][j];
            JT[9 + i][3 + j] = A[i][j];
        }
    for (int j = 0; j < 6; j++) JT[12][j] = r[j];
    /* J_i^T = -Ad(z^-1)^T J_l^-1(r)^T; J_l^-1(r)^T = J_j^T with each 3x3 block transposed */
    double JlT[6][6];
    for (int bi = 0; bi < 2; bi++)
        for (int bj = 0; bj < 2; bj++)
            for (int a = 0; a < 3; a++)
                for (int b = 0; b < 3; b++) JlT[3 * bi + a][3 * bj + b] = JT[6 + 3 * bi + b][3 * bj + a];
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) {
            double acc = 0.0;
            for (int m = 0; m < 6; m++) acc += nadz[6 * i + m] * JlT[m][j];
            JT[i][j] = acc;
        }
}

/* -- Python entry points ---------------------------------------------------------------------- */
static int check_nargs(Py_ssize_t nargs, Py_ssize_t want, const char *fn) {
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "%s() takes %zd arguments (%zd given)", fn, want, nargs);
        return -1;
    }
    return 0;
}

static PyObject *py_residuals(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 10, "residuals") < 0) return NULL;
    static const char *names[10] = {"P", "ii", "jj", "zt", "zq", "L", "r", "theta2", "c", "s"};
    Buf b[10];
    memset(b, 0, sizeof(b));
    Py_ssize_t N = get_rows(args[0], &b[0], names[0], 7, "(N, 7)");
    if (N < 0) goto fail;
    if (get_buf(args[1], &b[1], names[1], 'q', -1, 0) < 0) goto fail;
    Py_ssize_t E = nvals(&b[1]);
    const Py_ssize_t per[10] = {0, 1, 1, 3, 4, 36, 6, 1, 1, 1};
    for (int k = 2; k < 10; k++)
        if (get_buf(args[k], &b[k], names[k], k == 2 ? 'q' : 'd', per[k] * E, k >= 6) < 0) goto fail;
    const double *P = b[0].view.buf, *zt = b[3].view.buf, *zq = b[4].view.buf, *L = b[5].view.buf;
    const long long *ii = b[1].view.buf, *jj = b[2].view.buf;
    double *r = b[6].view.buf, *theta2 = b[7].view.buf, *c = b[8].view.buf, *s = b[9].view.buf;
    for (Py_ssize_t e = 0; e < E; e++)
        if (ii[e] < 0 || ii[e] >= N || jj[e] < 0 || jj[e] >= N) {
            PyErr_Format(PyExc_ValueError, "edge %zd: pose index (%lld, %lld) out of range [0, %zd)", e, ii[e],
                         jj[e], N);
            goto fail;
        }
    double chi2 = 0.0;
    Py_ssize_t bad = -1;
    long long bi = 0, bj = 0;
    Py_BEGIN_ALLOW_THREADS;
    for (Py_ssize_t e = 0; e < E; e++) {
        /* each index read once and that copy checked: ii/jj may alias an output or change in another thread */
        long long i = ii[e], j = jj[e];
        if (i < 0 || i >= N || j < 0 || j >= N) {
            bad = e, bi = i, bj = j;
            break;
        }
        double *re = r + 6 * e;
        residual(P + 7 * i, P + 7 * j, zt + 3 * e, zq + 4 * e, re, theta2 + e, c + e);
        /* s = |L^T r|^2 (the chi2 of the edge) */
        const double *Le = L + 36 * e;
        double se = 0.0;
        for (int j = 0; j < 6; j++) {
            double u = 0.0;
            for (int i = 0; i < 6; i++) u += re[i] * Le[6 * i + j]; /* any L with L L^T = Omega */
            se += u * u;
        }
        s[e] = se;
        chi2 += se;
    }
    Py_END_ALLOW_THREADS;
    if (bad >= 0) {
        PyErr_Format(PyExc_ValueError, "edge %zd: pose index (%lld, %lld) out of range [0, %zd)", bad, bi, bj, N);
        goto fail;
    }
    release(b, 10);
    return PyFloat_FromDouble(chi2);
fail:
    release(b, 10);
    return NULL;
}

static PyObject *py_linearize(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 9, "linearize") < 0) return NULL;
    static const char *names[9] = {"r", "theta2", "c", "neg_adz_t", "L", "w", "rows", "dims", "F"};
    Buf b[9];
    memset(b, 0, sizeof(b));
    if (get_buf(args[6], &b[6], names[6], 'q', -1, 0) < 0 || get_buf(args[7], &b[7], names[7], 'q', -1, 0) < 0)
        goto fail;
    Py_ssize_t nr = nvals(&b[6]), k = nvals(&b[7]);
    const long long *rows_in = b[6].view.buf, *dims_in = b[7].view.buf;
    int rows[13], dims[6]; /* validated local copies: the loop below runs without the GIL */
    if (k < 1 || k > 6 || nr < 1 || nr > 13) {
        PyErr_Format(PyExc_ValueError, "rows/dims: expected 1..13 rows and 1..6 dims, got %zd and %zd", nr, k);
        goto fail;
    }
    for (Py_ssize_t a = 0; a < nr; a++) {
        long long v = rows_in[a];
        if (v < 0 || v >= 13) {
            PyErr_Format(PyExc_ValueError, "rows[%zd] = %lld is out of range [0, 13)", a, v);
            goto fail;
        }
        rows[a] = (int)v;
    }
    for (Py_ssize_t a = 0; a < k; a++) {
        long long v = dims_in[a];
        if (v < 0 || v >= 6) {
            PyErr_Format(PyExc_ValueError, "dims[%zd] = %lld is out of range [0, 6)", a, v);
            goto fail;
        }
        dims[a] = (int)v;
    }
    Py_ssize_t E = get_rows(args[0], &b[0], names[0], 6, "(E, 6)");
    if (E < 0) goto fail;
    const Py_ssize_t per[6] = {6, 1, 1, 36, k * k, 1};
    for (int q = 1; q < 6; q++) {
        if (q == 5 && args[5] == Py_None) continue;
        if (get_buf(args[q], &b[q], names[q], 'd', per[q] * E, 0) < 0) goto fail;
    }
    if (get_buf(args[8], &b[8], names[8], 'd', nr * nr * E, 1) < 0) goto fail;
    const double *r = b[0].view.buf, *theta2 = b[1].view.buf, *c = b[2].view.buf, *nadz = b[3].view.buf,
                 *L = b[4].view.buf, *w = b[5].held ? b[5].view.buf : NULL;
    double *F = b[8].view.buf;
    Py_BEGIN_ALLOW_THREADS;
    double JT[13][6], AT[13][6];
    for (Py_ssize_t e = 0; e < E; e++) {
        jacobians_t(r + 6 * e, theta2[e], c[e], nadz + 36 * e, JT);
        /* whitened rows AT = JT[rows][:, dims] L, times sqrt(w) */
        const double *Le = L + k * k * e;
        double sw = w ? sqrt(w[e]) : 1.0;
        for (Py_ssize_t a = 0; a < nr; a++) {
            const double *row = JT[rows[a]];
            for (Py_ssize_t j = 0; j < k; j++) {
                double acc = 0.0;
                for (Py_ssize_t m = 0; m < k; m++) acc += row[dims[m]] * Le[k * m + j];
                AT[a][j] = sw * acc;
            }
        }
        /* F = AT AT^T: every block of H, the gradient and chi2 of the edge at once */
        double *Fe = F + nr * nr * e;
        for (Py_ssize_t a = 0; a < nr; a++)
            for (Py_ssize_t bb = 0; bb <= a; bb++) {
                double acc = 0.0;
                for (Py_ssize_t j = 0; j < k; j++) acc += AT[a][j] * AT[bb][j];
                Fe[nr * a + bb] = Fe[nr * bb + a] = acc;
            }
    }
    Py_END_ALLOW_THREADS;
    release(b, 9);
    Py_RETURN_NONE;
fail:
    release(b, 9);
    return NULL;
}

static PyObject *py_retract(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 3, "retract") < 0) return NULL;
    Buf b[3];
    memset(b, 0, sizeof(b));
    Py_ssize_t N = get_rows(args[0], &b[0], "P", 7, "(N, 7)");
    if (N < 0) goto fail;
    if (get_buf(args[1], &b[1], "xi", 'd', 6 * N, 0) < 0 || get_buf(args[2], &b[2], "out", 'd', 7 * N, 1) < 0)
        goto fail;
    const double *P = b[0].view.buf, *xi = b[1].view.buf;
    double *out = b[2].view.buf;
    const double tmin = pow(DBL_MIN, 0.25);
    Py_BEGIN_ALLOW_THREADS;
    for (Py_ssize_t n = 0; n < N; n++) {
        const double *p = P + 7 * n, *rho = xi + 6 * n, *phi = rho + 3;
        double theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2];
        double t = sqrt(theta2);
        if (t < tmin) t = tmin;
        double sh = sin(0.5 * t), k = sh / t, a = 2.0 * k * k;
        double bcoef = theta2 < SMALL2 ? 1.0 / 6.0 - theta2 / 120.0 : (t - sin(t)) / (t * t * t);
        double pxr[3], ppxr[3], te[3], qe[4], dt[3], q[4];
        cross(phi, rho, pxr);
        cross(phi, pxr, ppxr);
        for (int i = 0; i < 3; i++) te[i] = rho[i] + a * pxr[i] + bcoef * ppxr[i];
        qe[0] = k * phi[0], qe[1] = k * phi[1], qe[2] = k * phi[2], qe[3] = cos(0.5 * t);
        rotate(p + 3, te, dt);
        qmul(p + 3, qe, q);
        double *o = out + 7 * n;
        o[0] = p[0] + dt[0], o[1] = p[1] + dt[1], o[2] = p[2] + dt[2];
        o[3] = q[0], o[4] = q[1], o[5] = q[2], o[6] = q[3];
    }
    Py_END_ALLOW_THREADS;
    release(b, 3);
    Py_RETURN_NONE;
fail:
    release(b, 3);
    return NULL;
}

/* z^-1 = (zt, zq) and -Ad(z^-1)^T (E, 6, 6) of the measurements z (E, 7) (HostProblem's setup) */
static PyObject *py_measurement_terms(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 4, "measurement_terms") < 0) return NULL;
    Buf b[4];
    memset(b, 0, sizeof(b));
    Py_ssize_t E = get_rows(args[0], &b[0], "meas", 7, "(E, 7)");
    if (E < 0) goto fail;
    if (get_buf(args[1], &b[1], "zt", 'd', 3 * E, 1) < 0 || get_buf(args[2], &b[2], "zq", 'd', 4 * E, 1) < 0 ||
        get_buf(args[3], &b[3], "neg_adz_t", 'd', 36 * E, 1) < 0)
        goto fail;
    const double *Z = b[0].view.buf;
    double *zt = b[1].view.buf, *zq = b[2].view.buf, *nadz = b[3].view.buf;
    for (Py_ssize_t e = 0; e < E; e++) {
        const double *t = Z + 7 * e, *q = t + 3;
        double R[3][3], ex[3], col[3], H[3][3];
        /* R = R(z) = R(z^-1)^T, column by column */
        for (int j = 0; j < 3; j++) {
            ex[0] = ex[1] = ex[2] = 0.0;
            ex[j] = 1.0;
            rotate(q, ex, col);
            R[0][j] = col[0], R[1][j] = col[1], R[2][j] = col[2];
        }
        double *zte = zt + 3 * e, *zqe = zq + 4 * e, *N = nadz + 36 * e;
        zqe[0] = -q[0], zqe[1] = -q[1], zqe[2] = -q[2], zqe[3] = q[3];
        for (int j = 0; j < 3; j++) zte[j] = -(t[0] * R[0][j] + t[1] * R[1][j] + t[2] * R[2][j]);
        hat(zte, H);
        /* -Ad(z^-1)^T = [[-R^T, 0], [R^T hat(t), -R^T]] with R = R(z^-1), t = t(z^-1) */
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                N[6 * i + j] = -R[i][j];
                N[6 * i + 3 + j] = 0.0;
                N[6 * (3 + i) + 3 + j] = -R[i][j];
                N[6 * (3 + i) + j] = R[i][0] * H[0][j] + R[i][1] * H[1][j] + R[i][2] * H[2][j];
            }
    }
    release(b, 4);
    Py_RETURN_NONE;
fail:
    release(b, 4);
    return NULL;
}

/* Add each edge's F (E, 2k+1, 2k+1) into the dense H (m, m) and g (m,): rows 0..k-1 of F belong to
 * variable var[ii[e]], rows k..2k-1 to var[jj[e]] (-1: a fixed pose, skipped), row 2k is the residual's. */
static PyObject *py_assemble_dense(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 6, "assemble_dense") < 0) return NULL;
    Buf b[6];
    memset(b, 0, sizeof(b));
    if (get_buf(args[1], &b[1], "ii", 'q', -1, 0) < 0 || get_buf(args[3], &b[3], "var", 'q', -1, 0) < 0 ||
        get_buf(args[5], &b[5], "g", 'd', -1, 1) < 0)
        goto fail;
    Py_ssize_t E = nvals(&b[1]), N = nvals(&b[3]), m = nvals(&b[5]);
    if (m > 0 && m > PY_SSIZE_T_MAX / 8 / m) {
        PyErr_Format(PyExc_ValueError, "g: %zd unknowns is too many for a dense H", m);
        goto fail;
    }
    if (get_buf(args[2], &b[2], "jj", 'q', E, 0) < 0 || get_buf(args[0], &b[0], "F", 'd', -1, 0) < 0 ||
        get_buf(args[4], &b[4], "H", 'd', m * m, 1) < 0)
        goto fail;
    Py_ssize_t q = E ? nvals(&b[0]) / E : 0, nr = 1, k;
    while (nr * nr < q) nr++;
    k = (nr - 1) / 2;
    if (nr * nr * E != nvals(&b[0]) || (E && (nr % 2 != 1 || k < 1))) {
        PyErr_Format(PyExc_ValueError, "F: expected (%zd, 2k+1, 2k+1) values, got %zd", E, nvals(&b[0]));
        goto fail;
    }
    const double *F = b[0].view.buf;
    const long long *ii = b[1].view.buf, *jj = b[2].view.buf, *var = b[3].view.buf;
    double *H = b[4].view.buf, *g = b[5].view.buf;
    for (Py_ssize_t e = 0; e < E; e++) {
        if (ii[e] < 0 || ii[e] >= N || jj[e] < 0 || jj[e] >= N) {
            PyErr_Format(PyExc_ValueError, "edge %zd: pose index (%lld, %lld) out of range [0, %zd)", e, ii[e],
                         jj[e], N);
            goto fail;
        }
        long long v[2] = {var[ii[e]], var[jj[e]]};
        if (v[0] >= m / k || v[1] >= m / k) { /* no (v + 1) * k: it overflows for huge v */
            PyErr_Format(PyExc_ValueError, "edge %zd: variable (%lld, %lld) out of range for %zd unknowns", e, v[0],
                         v[1], m);
            goto fail;
        }
        const double *Fe = F + nr * nr * e;
        for (Py_ssize_t a = 0; a < 2 * k; a++) {
            long long va = v[a / k];
            if (va < 0) continue;
            Py_ssize_t ra = va * k + a % k;
            const double *Fa = Fe + nr * a;
            g[ra] += Fa[2 * k];
            for (int side = 0; side < 2; side++) {
                long long vb = v[side];
                if (vb < 0) continue;
                double *Hrow = H + m * ra + vb * k;
                const double *Fab = Fa + side * k;
                for (Py_ssize_t c2 = 0; c2 < k; c2++) Hrow[c2] += Fab[c2];
            }
        }
    }
    release(b, 6);
    Py_RETURN_NONE;
fail:
    release(b, 6);
    return NULL;
}

/* out = P with each quaternion scaled to unit norm (P (N, 7), the rows of poses or measurements) */
static PyObject *py_unit_poses(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 2, "unit_poses") < 0) return NULL;
    Buf b[2];
    memset(b, 0, sizeof(b));
    Py_ssize_t N = get_rows(args[0], &b[0], "P", 7, "(N, 7)");
    if (N < 0) goto fail;
    if (get_buf(args[1], &b[1], "out", 'd', 7 * N, 1) < 0) goto fail;
    const double *P = b[0].view.buf;
    double *out = b[1].view.buf;
    for (Py_ssize_t n = 0; n < N; n++) {
        const double *p = P + 7 * n;
        double *o = out + 7 * n;
        double nq = sqrt(((p[3] * p[3] + p[4] * p[4]) + p[5] * p[5]) + p[6] * p[6]);
        o[0] = p[0], o[1] = p[1], o[2] = p[2];
        o[3] = p[3] / nq, o[4] = p[4] / nq, o[5] = p[5] / nq, o[6] = p[6] / nq;
    }
    release(b, 2);
    Py_RETURN_NONE;
fail:
    release(b, 2);
    return NULL;
}

/* Lower Cholesky factors L (E, 6, 6) of the information matrices (E, 6, 6), from their lower triangles.
 * Returns -1, or the first edge whose matrix is not positive definite (or not finite), or, when `check`,
 * not symmetric: |A - A^T| > rtol * max(max diag, DBL_MIN) (slam.graph.optimizer._information_factor's rule,
 * which the caller then runs to raise its error). */
static PyObject *py_information_factors(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 4, "information_factors") < 0) return NULL;
    int check = PyObject_IsTrue(args[2]);
    double rtol = PyFloat_AsDouble(args[3]);
    if (check < 0 || (rtol == -1.0 && PyErr_Occurred())) return NULL;
    Buf b[2];
    memset(b, 0, sizeof(b));
    Py_ssize_t E = get_rows(args[0], &b[0], "info", 36, "(E, 6, 6)");
    if (E < 0) goto fail;
    if (get_buf(args[1], &b[1], "L", 'd', 36 * E, 1) < 0) goto fail;
    const double *info = b[0].view.buf;
    double *Lall = b[1].view.buf;
    Py_ssize_t bad = -1;
    for (Py_ssize_t e = 0; e < E && bad < 0; e++) {
        const double *A = info + 36 * e;
        double *L = Lall + 36 * e;
        if (check) {
            double scale = DBL_MIN, asym = 0.0;
            for (int i = 0; i < 6; i++)
                if (A[7 * i] > scale) scale = A[7 * i];
            for (int i = 0; i < 6; i++)
                for (int j = 0; j < i; j++) {
                    double d = fabs(A[6 * i + j] - A[6 * j + i]);
                    if (!(d <= asym)) asym = d; /* a NaN sticks */
                }
            if (!(asym <= rtol * scale)) {
                bad = e;
                break;
            }
        }
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j <= i; j++) {
                double s = A[6 * i + j];
                for (int m = 0; m < j; m++) s -= L[6 * i + m] * L[6 * j + m];
                if (j < i) {
                    L[6 * i + j] = s / L[7 * j];
                } else if (s > 0.0 && isfinite(s)) {
                    L[7 * i] = sqrt(s);
                } else {
                    bad = e;
                }
            }
            for (int j = i + 1; j < 6; j++) L[6 * i + j] = 0.0;
            if (bad >= 0) break;
        }
        for (int q = 0; q < 36 && bad < 0; q++)
            if (!isfinite(L[q])) bad = e;
    }
    release(b, 2);
    return PyLong_FromSsize_t(bad);
fail:
    release(b, 2);
    return NULL;
}

/* -- supernodes of slam.graph.cholesky (small fronts: plain loops beat the per-call cost of LAPACK) -- */
static inline double dotn(const double *a, const double *b, Py_ssize_t n) {
    double s0 = 0.0, s1 = 0.0;
    Py_ssize_t i = 0;
    for (; i + 2 <= n; i += 2) {
        s0 += a[i] * b[i];
        s1 += a[i + 1] * b[i + 1];
    }
    if (i < n) s0 += a[i] * b[i];
    return s0 + s1;
}

/* Position of entry (a, b), a >= b, of a d x d lower triangle in LAPACK's rectangular full packed order
 * (transr='N', uplo='U' of the Fortran view), the order of slam.graph.cholesky._rfp_rows_cols: with
 * h = d / 2 and lda = d + 1 - d % 2, row a >= h is column a - h (entries 0..a), a row a < h lies in
 * column b below it, at row a + h + 1. */
static inline Py_ssize_t rfp_pos(Py_ssize_t a, Py_ssize_t b, Py_ssize_t d) {
    Py_ssize_t h = d / 2, lda = d + 1 - d % 2;
    return a >= h ? (a - h) * lda + b : b * lda + a + h + 1;
}

/* Whether two buffers share memory: an index array inside the array a kernel writes would change
 * after its check (the indices are checked once, before the loop) */
static int overlaps(const Buf *a, const Buf *b) {
    uintptr_t a0 = (uintptr_t)a->view.buf, b0 = (uintptr_t)b->view.buf;
    return a->view.len > 0 && b->view.len > 0 && a0 < b0 + (uintptr_t)b->view.len &&
           b0 < a0 + (uintptr_t)a->view.len;
}

/* Integers (anything with __index__, e.g. numpy ints) into out[0..n-1]; -1 with an exception set */
static int as_sizes(PyObject *const *args, int n, Py_ssize_t *out) {
    for (int i = 0; i < n; i++) {
        out[i] = PyNumber_AsSsize_t(args[i], PyExc_OverflowError);
        if (out[i] == -1 && PyErr_Occurred()) return -1;
    }
    return 0;
}

/* Common checks of a group of B supernodes (panels (m, p) row-major at offset + s m p of buf) */
static int check_group(Py_ssize_t nbuf, Py_ssize_t offset, Py_ssize_t B, Py_ssize_t p, Py_ssize_t m) {
    /* no sum or product that can overflow: offset and B are any Python ints */
    if (offset < 0 || B < 0 || p < 1 || m < p || m > 100000 || offset > nbuf || B > (nbuf - offset) / (m * p)) {
        PyErr_Format(PyExc_ValueError, "group: offset %zd, %zd supernodes of %zd x %zd panels do not fit a buffer of "
                     "%zd values", offset, B, m, p, nbuf);
        return -1;
    }
    return 0;
}

/* factor_group(buf, offset, B, p, m, upd) -> info: factor B supernodes in place in their panels
 * [L11; L21] (L11 L11^T = F11, L21 = F21 L11^-T) and add each update -L21 L21^T (packed, in the order
 * of rfp_pos) at its positions upd (int32, B d (d + 1) / 2) of buf; info = s + 1 for the first supernode
 * s whose pivot block is not positive definite (or not finite), else 0 (its upper triangle is zeroed). */
static PyObject *py_factor_group(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 6, "factor_group") < 0) return NULL;
    Py_ssize_t v[4];
    if (as_sizes(args + 1, 4, v) < 0) return NULL;
    Py_ssize_t offset = v[0], B = v[1], p = v[2], m = v[3];
    Buf b[2];
    memset(b, 0, sizeof(b));
    long info = 0;
    if (get_buf(args[0], &b[0], "buf", 'd', -1, 1) < 0 || get_buf(args[5], &b[1], "upd", 'i', -1, 0) < 0) goto fail;
    Py_ssize_t nbuf = nvals(&b[0]), d = m - p, nl = d * (d + 1) / 2;
    if (check_group(nbuf, offset, B, p, m) < 0) goto fail;
    if (nvals(&b[1]) != B * nl) {
        PyErr_Format(PyExc_ValueError, "upd: expected %zd values, got %zd", B * nl, nvals(&b[1]));
        goto fail;
    }
    if (overlaps(&b[0], &b[1])) {
        PyErr_SetString(PyExc_ValueError, "upd: shares memory with buf");
        goto fail;
    }
    double *buf = b[0].view.buf;
    const int *upd = b[1].view.buf;
    for (Py_ssize_t q = 0; q < B * nl; q++)
        if (upd[q] < 0 || upd[q] >= nbuf) {
            PyErr_Format(PyExc_ValueError, "upd[%zd] = %d is out of range [0, %zd)", q, upd[q], nbuf);
            goto fail;
        }
    /* the GIL stays held: upd and buf are Python arrays another thread could change after the checks */
    for (Py_ssize_t sn = 0; sn < B && !info; sn++) {
        double *L = buf + offset + sn * m * p; /* rows 0..p-1: L11, rows p..m-1: L21 (row stride p) */
        for (Py_ssize_t j = 0; j < p && !info; j++) {
            double *Lj = L + p * j;
            double s = Lj[j] - dotn(Lj, Lj, j);
            if (!(s > 0.0) || !isfinite(s)) {
                info = (long)sn + 1;
                break;
            }
            double djj = sqrt(s);
            Lj[j] = djj;
            for (Py_ssize_t c = j + 1; c < p; c++) Lj[c] = 0.0;
            for (Py_ssize_t i = j + 1; i < m; i++) { /* the rest of column j, L11 and L21 alike */
                double *Li = L + p * i;
                Li[j] = (Li[j] - dotn(Li, Lj, j)) / djj;
            }
        }
        if (info) break;
        const double *L21 = L + p * p;
        const int *u = upd + sn * nl;
        for (Py_ssize_t a = 0; a < d; a++)
            for (Py_ssize_t c = 0; c <= a; c++) buf[u[rfp_pos(a, c, d)]] -= dotn(L21 + p * a, L21 + p * c, p);
    }
    release(b, 2);
    return PyLong_FromLong(info);
fail:
    release(b, 2);
    return NULL;
}

/* solve_group(buf, offset, B, p, m, col0, rows, y, forward): for each of the B supernodes (columns
 * col0 + s p .. + p of the permuted system, its L21 rows `rows` (int64, B d)):
 * forward:  y_c = L11^-1 y_c, then y[rows] -= L21 y_c;  backward: y_c -= L21^T y[rows], y_c = L11^-T y_c. */
static PyObject *py_solve_group(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 9, "solve_group") < 0) return NULL;
    Py_ssize_t v[5];
    if (as_sizes(args + 1, 5, v) < 0) return NULL;
    Py_ssize_t offset = v[0], B = v[1], p = v[2], m = v[3], col0 = v[4];
    int forward = PyObject_IsTrue(args[8]);
    if (forward < 0) return NULL;
    Buf b[3];
    memset(b, 0, sizeof(b));
    if (get_buf(args[0], &b[0], "buf", 'd', -1, 0) < 0 || get_buf(args[6], &b[1], "rows", 'q', -1, 0) < 0 ||
        get_buf(args[7], &b[2], "y", 'd', -1, 1) < 0)
        goto fail;
    Py_ssize_t nbuf = nvals(&b[0]), n = nvals(&b[2]), d = m - p;
    if (check_group(nbuf, offset, B, p, m) < 0) goto fail;
    if (nvals(&b[1]) != B * d || col0 < 0 || col0 > n || B > (n - col0) / p) {
        PyErr_Format(PyExc_ValueError, "rows/col0: expected %zd rows and %zd columns from %zd within %zd, got %zd rows",
                     B * d, B * p, col0, n, nvals(&b[1]));
        goto fail;
    }
    if (overlaps(&b[1], &b[2])) {
        PyErr_SetString(PyExc_ValueError, "rows: shares memory with y");
        goto fail;
    }
    const double *buf = b[0].view.buf;
    const long long *rows = b[1].view.buf;
    double *y = b[2].view.buf;
    for (Py_ssize_t q = 0; q < B * d; q++)
        if (rows[q] < 0 || rows[q] >= n) {
            PyErr_Format(PyExc_ValueError, "rows[%zd] = %lld is out of range [0, %zd)", q, rows[q], n);
            goto fail;
        }
    for (Py_ssize_t sn = 0; sn < B; sn++) {
        const double *L = buf + offset + sn * m * p, *L21 = L + p * p;
        const long long *r = rows + sn * d;
        double *yc = y + col0 + sn * p;
        if (forward) {
            for (Py_ssize_t j = 0; j < p; j++) yc[j] = (yc[j] - dotn(L + p * j, yc, j)) / L[p * j + j];
            for (Py_ssize_t a = 0; a < d; a++) y[r[a]] -= dotn(L21 + p * a, yc, p);
        } else {
            for (Py_ssize_t a = 0; a < d; a++) {
                double ya = y[r[a]];
                const double *La = L21 + p * a;
                for (Py_ssize_t c = 0; c < p; c++) yc[c] -= La[c] * ya;
            }
            for (Py_ssize_t j = p - 1; j >= 0; j--) {
                double s = yc[j];
                for (Py_ssize_t i = j + 1; i < p; i++) s -= L[p * i + j] * yc[i];
                yc[j] = s / L[p * j + j];
            }
        }
    }
    release(b, 3);
    Py_RETURN_NONE;
fail:
    release(b, 3);
    return NULL;
}

/* Move poses P (N, 7) rigidly so that pose 0 lands on anchor (7,): out = anchor P_0^-1 P, out_0 = anchor */
static PyObject *py_relocate(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs(nargs, 3, "relocate") < 0) return NULL;
    Buf b[3];
    memset(b, 0, sizeof(b));
    Py_ssize_t N = get_rows(args[0], &b[0], "P", 7, "(N >= 1, 7)");
    if (N < 0) goto fail;
    if (N < 1) {
        PyErr_SetString(PyExc_ValueError, "P: expected (N >= 1, 7) values, got 0");
        goto fail;
    }
    if (get_buf(args[1], &b[1], "anchor", 'd', 7, 0) < 0 || get_buf(args[2], &b[2], "out", 'd', 7 * N, 1) < 0)
        goto fail;
    const double *P = b[0].view.buf, *a = b[1].view.buf;
    double *out = b[2].view.buf;
    double cq[4], ct[3], rt[3];
    qmul_conj(a + 3, P + 3, cq); /* rotation of anchor P_0^-1 */
    rotate(cq, P, rt);
    for (int i = 0; i < 3; i++) ct[i] = a[i] - rt[i];
    for (Py_ssize_t n = 0; n < N; n++) {
        const double *p = P + 7 * n;
        double *o = out + 7 * n, q[4];
        rotate(cq, p, rt);
        qmul(cq, p + 3, q);
        o[0] = ct[0] + rt[0], o[1] = ct[1] + rt[1], o[2] = ct[2] + rt[2];
        o[3] = q[0], o[4] = q[1], o[5] = q[2], o[6] = q[3];
    }
    memmove(out, a, 7 * sizeof(double));
    release(b, 3);
    Py_RETURN_NONE;
fail:
    release(b, 3);
    return NULL;
}

static PyObject *py_set_constants(PyObject *self, PyObject *args) {
    (void)self;
    double small, small_q, s[9];
    if (!PyArg_ParseTuple(args, "dd(ddddddddd)", &small, &small_q, &s[0], &s[1], &s[2], &s[3], &s[4], &s[5],
                          &s[6], &s[7], &s[8]))
        return NULL;
    SMALL2 = small * small;
    SMALL_Q2 = small_q * small_q;
    for (int i = 0; i < 9; i++) QS[i / 3][i % 3] = s[i];
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"residuals", (PyCFunction)(void (*)(void))py_residuals, METH_FASTCALL,
     "residuals(P, ii, jj, zt, zq, L, r, theta2, c, s) -> chi2: r = Log(z^-1 T_i^-1 T_j) (E, 6), theta^2 and c "
     "(E,) for the Jacobians, s = |L^T r|^2 (E,) into the given buffers; returns sum(s)."},
    {"linearize", (PyCFunction)(void (*)(void))py_linearize, METH_FASTCALL,
     "linearize(r, theta2, c, neg_adz_t, L, w, rows, dims, F): per edge F = A A^T (E, n, n) with "
     "A = [J_i^T; J_j^T; r^T][rows][:, dims] L (sqrt(w) A when w is not None)."},
    {"retract", (PyCFunction)(void (*)(void))py_retract, METH_FASTCALL,
     "retract(P, xi, out): out = P exp(xi) for poses (N, 7) and steps [rho, phi] (N, 6)."},
    {"measurement_terms", (PyCFunction)(void (*)(void))py_measurement_terms, METH_FASTCALL,
     "measurement_terms(meas, zt, zq, neg_adz_t): z^-1 = (zt (E, 3), zq (E, 4)) and -Ad(z^-1)^T (E, 6, 6)."},
    {"assemble_dense", (PyCFunction)(void (*)(void))py_assemble_dense, METH_FASTCALL,
     "assemble_dense(F, ii, jj, var, H, g): add each edge's F (E, 2k+1, 2k+1) into H (m, m) and g (m,)."},
    {"unit_poses", (PyCFunction)(void (*)(void))py_unit_poses, METH_FASTCALL,
     "unit_poses(P, out): out = P (N, 7) with each quaternion scaled to unit norm."},
    {"information_factors", (PyCFunction)(void (*)(void))py_information_factors, METH_FASTCALL,
     "information_factors(info, L, check, rtol) -> int: lower Cholesky factors L (E, 6, 6); -1, or the first edge "
     "whose matrix is not positive definite (or, when check, not symmetric to rtol)."},
    {"factor_group", (PyCFunction)(void (*)(void))py_factor_group, METH_FASTCALL,
     "factor_group(buf, offset, B, p, m, upd) -> info: Cholesky of B supernodes in their panels, updates added "
     "at upd (int32, packed); 0 or the first failing supernode + 1."},
    {"solve_group", (PyCFunction)(void (*)(void))py_solve_group, METH_FASTCALL,
     "solve_group(buf, offset, B, p, m, col0, rows, y, forward): the forward (L) or backward (L^T) substitution "
     "of B supernodes on y."},
    {"relocate", (PyCFunction)(void (*)(void))py_relocate, METH_FASTCALL,
     "relocate(P, anchor, out): out = anchor P_0^-1 P (N, 7), with out_0 = anchor exactly."},
    {"set_constants", py_set_constants, METH_VARARGS,
     "set_constants(small, small_q, series9): the series thresholds and Barfoot's Q series (row-major 3x3)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "The per-edge loops of slam.graph.accel.host in C (see _kernels.c).", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernels(void) {
    PyObject *mod = PyModule_Create(&module);
    if (mod && PyModule_AddIntConstant(mod, "ABI", 2) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
