/* The per-sample loops of stage 2's LM for the core model (K, b; no effect term) under the
 * default fit's kernels (Cauchy, Geman–McClure): the algebra of streamcal/fitting/lm_blocks.py
 * (tangent-plane direction blocks, Triggs weights multiplied out) in one pass per call, every
 * per-sample quantity in registers. Python side: streamcal/fitting/lm_compiled.py.
 *
 * Why C and not numpy: at N = 1000 numpy's ~85 calls per iteration cost more in call overhead
 * than in arithmetic; why C and not numba: numba's import costs ~0.5 s and ~100 MB per process,
 * more than a whole one-shot fit. Arrays come in through the buffer protocol (C-contiguous
 * float64), so no numpy headers are needed to build this; the pairs of samples use GCC/Clang
 * vector extensions, so this builds with either (not MSVC: there the numpy engine runs).
 *
 * Layouts: m, x (3,N) rows x0.., x1.., x2..; K (3,3) row-major; b (3,); full (12,) the step of
 * (K, b) with full[3c + a] = ΔK[a, c] and full[9 + a] = Δb[a]; work (14,N), one row of N per
 * per-sample number: T (3,2) row-major, C = H_t⁻¹ Fᵀ (2,3) row-major, z = H_t⁻¹ gt (2,);
 * acc (72,) = Σ x̄_c x̄_d Q over the pairs c ≤ d of x̄ = [x; 1] (10 rows × Q's 6 unique entries),
 * then Σ x̄_c y (4 × 3).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#define S_FLOOR 1e-12
#define D_MIN 0.25
#define WORK 14
#define KERNEL_CAUCHY 0
#define KERNEL_GM 1
#ifndef LMCORE_SOURCE_SHA256  /* setup.py passes the source's hash; other builds say so */
#define LMCORE_SOURCE_SHA256 "unknown"
#endif

typedef struct {
    Py_buffer view;
    int held;
} buf_t;

static void release(buf_t *bufs, int n)
{
    for (int i = 0; i < n; i++)
        if (bufs[i].held)
            PyBuffer_Release(&bufs[i].view);
}

/* The buffer of obj as a C-contiguous float64 array of shape (rows, cols), or (rows,) when
 * cols < 0 (writable when asked); else an exception naming the argument. */
static int get_doubles(PyObject *obj, buf_t *buf, Py_ssize_t rows, Py_ssize_t cols, int writable,
                       const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    buf->held = 0;
    if (PyObject_GetBuffer(obj, &buf->view, flags) < 0)
        return -1;
    buf->held = 1;
    if (buf->view.itemsize != sizeof(double) || buf->view.format == NULL
        || strcmp(buf->view.format, "d") != 0) {
        PyErr_Format(PyExc_TypeError, "%s must hold float64 values", name);
        return -1;
    }
    int ndim = cols < 0 ? 1 : 2;
    const Py_ssize_t *shape = buf->view.shape;
    if (buf->view.ndim != ndim || shape[0] != rows || (ndim == 2 && shape[1] != cols)) {
        char want[64], got[64];
        if (ndim == 1)
            PyOS_snprintf(want, sizeof want, "(%zd,)", rows);
        else
            PyOS_snprintf(want, sizeof want, "(%zd, %zd)", rows, cols);
        if (buf->view.ndim == 1)
            PyOS_snprintf(got, sizeof got, "(%zd,)", shape[0]);
        else if (buf->view.ndim == 2)
            PyOS_snprintf(got, sizeof got, "(%zd, %zd)", shape[0], shape[1]);
        else
            PyOS_snprintf(got, sizeof got, "%d dimensions", buf->view.ndim);
        PyErr_Format(PyExc_ValueError, "%s must have shape %s, got %s", name, want, got);
        return -1;
    }
    return 0;
}

/* The sample count n and kernel id of a call, checked before any buffer is sized by them. */
static int check_n_kid(Py_ssize_t n, int kid)
{
    if (n < 0 || n > PY_SSIZE_T_MAX / (WORK * (Py_ssize_t)sizeof(double))) {
        PyErr_Format(PyExc_ValueError, "n must be a sample count, got %zd", n);
        return -1;
    }
    if (kid != KERNEL_CAUCHY && kid != KERNEL_GM) {
        PyErr_Format(PyExc_ValueError, "kernel_id must be %d (Cauchy) or %d (Geman-McClure), got %d",
                     KERNEL_CAUCHY, KERNEL_GM, kid);
        return -1;
    }
    return 0;
}

/* r = K x + b − m of sample j of (3,n) rows, as NumpyEngine.cost computes it: (K x − m) + b. */
static inline void residual(const double *m, const double *x, const double *K, const double *b,
                            Py_ssize_t n, Py_ssize_t j, double r[3])
{
    double x0 = x[j], x1 = x[n + j], x2 = x[2 * n + j];
    r[0] = (K[0] * x0 + K[1] * x1 + K[2] * x2) - m[j] + b[0];
    r[1] = (K[3] * x0 + K[4] * x1 + K[5] * x2) - m[n + j] + b[1];
    r[2] = (K[6] * x0 + K[7] * x1 + K[8] * x2) - m[2 * n + j] + b[2];
}

/* ρ′ and ρ″ of the kernel at s = ‖r‖², as kernels.Cauchy/GemanMcClure.derivatives compute them. */
static inline void derivatives(int kid, double t2, double s, double *d1, double *d2)
{
    if (kid == KERNEL_CAUCHY) {
        double q = 1.0 + s / t2;
        double f = 1.0 / q;
        *d1 = f;
        *d2 = (-1.0 / t2) * (f * f);
    } else {
        double f = t2 / (t2 + s);
        double g = f * f;
        *d1 = g;
        *d2 = (-2.0 / t2) * (g * f);
    }
}

static PyObject *lm_cost(PyObject *self, PyObject *args)
{
    PyObject *o_m, *o_x, *o_K, *o_b;
    int kid;
    double t2;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OOOOnid", &o_m, &o_x, &o_K, &o_b, &n, &kid, &t2))
        return NULL;
    buf_t bufs[4];
    memset(bufs, 0, sizeof bufs);
    if (check_n_kid(n, kid) || get_doubles(o_m, &bufs[0], 3, n, 0, "m")
        || get_doubles(o_x, &bufs[1], 3, n, 0, "x") || get_doubles(o_K, &bufs[2], 3, 3, 0, "K")
        || get_doubles(o_b, &bufs[3], 3, -1, 0, "b")) {
        release(bufs, 4);
        return NULL;
    }
    const double *m = bufs[0].view.buf, *x = bufs[1].view.buf, *K = bufs[2].view.buf,
                 *b = bufs[3].view.buf;
    double total = 0.0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++) {
        double r[3];
        residual(m, x, K, b, n, j, r);
        double s = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
        total += kid == KERNEL_CAUCHY ? t2 * log1p(s / t2) : s * t2 / (t2 + s);
    }
    Py_END_ALLOW_THREADS
    release(bufs, 4);
    return PyFloat_FromDouble(total);
}

/* Two samples per operation: GCC/Clang vector extensions (SSE2 on x86-64, NEON on aarch64; the
 * baseline of both, no flag needed). Each lane does the scalar arithmetic of one sample in the
 * same order; only the sums over samples are split in two lanes (even and odd samples). */
typedef double v2d __attribute__((vector_size(16)));
typedef long long v2l __attribute__((vector_size(16)));

static inline v2d vload(const double *p)
{
    v2d v;
    memcpy(&v, p, sizeof v);
    return v;
}

static inline v2d vsplat(double a) { return (v2d){a, a}; }

/* a where mask, else b (mask lanes all ones or all zeros, as vector comparisons give) */
static inline v2d vselect(v2l mask, v2d a, v2d b)
{
    return (v2d)(((v2l)a & mask) | ((v2l)b & ~mask));
}

/* The per-sample work of two samples: their shares of the Schur sums added to acc (lane-wise),
 * their T, C, z written to work (SoA, rows of n) for lanes < `lanes`. */
static inline void reduce_pair(const double *m, const double *x, const double *K, const double *b,
                               Py_ssize_t n, Py_ssize_t j, int lanes, int kid, double t2,
                               double lam, double *work, v2d *acc)
{
    v2d x0, x1, x2, m0, m1, m2;
    if (lanes == 2) {
        x0 = vload(x + j); x1 = vload(x + n + j); x2 = vload(x + 2 * n + j);
        m0 = vload(m + j); m1 = vload(m + n + j); m2 = vload(m + 2 * n + j);
    } else {  /* the last sample of an odd count, in both lanes; lane 1 is dropped */
        x0 = vsplat(x[j]); x1 = vsplat(x[n + j]); x2 = vsplat(x[2 * n + j]);
        m0 = vsplat(m[j]); m1 = vsplat(m[n + j]); m2 = vsplat(m[2 * n + j]);
    }
    const v2d one = vsplat(1.0), two = vsplat(2.0);
    v2d r0 = (vsplat(K[0]) * x0 + vsplat(K[1]) * x1 + vsplat(K[2]) * x2) - m0 + vsplat(b[0]);
    v2d r1 = (vsplat(K[3]) * x0 + vsplat(K[4]) * x1 + vsplat(K[5]) * x2) - m1 + vsplat(b[1]);
    v2d r2 = (vsplat(K[6]) * x0 + vsplat(K[7]) * x1 + vsplat(K[8]) * x2) - m2 + vsplat(b[2]);
    v2d s = r0 * r0 + r1 * r1 + r2 * r2;
    v2d d1, d2, T2 = vsplat(t2);
    if (kid == KERNEL_CAUCHY) {
        v2d f = one / (one + s / T2);
        d1 = f;
        d2 = vsplat(-1.0 / t2) * (f * f);
    } else {
        v2d f = T2 / (T2 + s);
        v2d g = f * f;
        d1 = g;
        d2 = vsplat(-2.0 / t2) * (g * f);
    }
    /* Triggs weights (kernels.triggs_weights): W = w I + e r rᵀ, gradient scale gw */
    const v2d tiny = vsplat(1e-300);
    v2d w = vselect(d1 > tiny, d1, tiny);
    v2d clamp = vsplat(D_MIN - 1.0) * w / s;
    v2d e = vselect(two * d2 > clamp, two * d2, clamp), gw = w;
    v2l low = s <= vsplat(S_FLOOR);
    if (low[0] || low[1]) {
        for (int k = 0; k < 2; k++) {
            if (!low[k])
                continue;
            double D = 1.0 + 2.0 * s[k] * d2[k] / w[k];
            e[k] = 0.0;
            gw[k] = w[k] / sqrt(D > D_MIN ? D : D_MIN);
        }
    }
    /* orthonormal tangent basis T (3,2) at x (Duff et al. 2017) */
    const v2d sign_bit = (v2d)(v2l){(long long)0x8000000000000000ULL, (long long)0x8000000000000000ULL};
    v2d sg = (v2d)(((v2l)x2 & (v2l)sign_bit) | (v2l)one);
    v2d a = vsplat(-1.0) / (sg + x2);
    v2d bb = x0 * x1 * a;
    v2d sx = sg * x0;
    v2d t00 = sx * x0 * a + one, t01 = bb;
    v2d t10 = sg * bb, t11 = x1 * x1 * a + sg;
    v2d t20 = -sx, t21 = -x1;
    /* D = K T (3,2), Dᵀr, H_t = 2 Dᵀ W D + λI, F = W D */
    v2d k0 = vsplat(K[0]), k1 = vsplat(K[1]), k2 = vsplat(K[2]), k3 = vsplat(K[3]), k4 = vsplat(K[4]);
    v2d k5 = vsplat(K[5]), k6 = vsplat(K[6]), k7 = vsplat(K[7]), k8 = vsplat(K[8]);
    v2d D00 = k0 * t00 + k1 * t10 + k2 * t20, D01 = k0 * t01 + k1 * t11 + k2 * t21;
    v2d D10 = k3 * t00 + k4 * t10 + k5 * t20, D11 = k3 * t01 + k4 * t11 + k5 * t21;
    v2d D20 = k6 * t00 + k7 * t10 + k8 * t20, D21 = k6 * t01 + k7 * t11 + k8 * t21;
    v2d dr0 = D00 * r0 + D10 * r1 + D20 * r2, dr1 = D01 * r0 + D11 * r1 + D21 * r2;
    v2d ww = two * w, we = two * e, L = vsplat(lam);
    v2d h00 = (D00 * D00 + D10 * D10 + D20 * D20) * ww + we * (dr0 * dr0) + L;
    v2d h01 = (D00 * D01 + D10 * D11 + D20 * D21) * ww + we * (dr0 * dr1);
    v2d h11 = (D01 * D01 + D11 * D11 + D21 * D21) * ww + we * (dr1 * dr1) + L;
    v2d er0 = e * r0, er1 = e * r1, er2 = e * r2;
    v2d F00 = w * D00 + er0 * dr0, F01 = w * D01 + er0 * dr1;
    v2d F10 = w * D10 + er1 * dr0, F11 = w * D11 + er1 * dr1;
    v2d F20 = w * D20 + er2 * dr0, F21 = w * D21 + er2 * dr1;
    v2d det = h00 * h11 - h01 * h01;
    v2d i00 = h11 / det, i01 = -h01 / det, i11 = h00 / det;
    /* C = H_t⁻¹ Fᵀ (2,3), z = H_t⁻¹ Tᵀ g_x */
    v2d c00 = i00 * F00 + i01 * F01, c01 = i00 * F10 + i01 * F11, c02 = i00 * F20 + i01 * F21;
    v2d c10 = i01 * F00 + i11 * F01, c11 = i01 * F10 + i11 * F11, c12 = i01 * F20 + i11 * F21;
    v2d g0 = (two * gw) * dr0, g1 = (two * gw) * dr1;
    v2d z0 = i00 * g0 + i01 * g1, z1 = i01 * g0 + i11 * g1;
    /* Q = 2W − 4 F C (unique entries), y = −2γ r + 2 F z */
    const v2d m4 = vsplat(-4.0);
    v2d q[6];
    q[0] = (F00 * c00 + F01 * c10) * m4 + (we * (r0 * r0) + ww);
    q[1] = (F00 * c01 + F01 * c11) * m4 + we * (r0 * r1);
    q[2] = (F00 * c02 + F01 * c12) * m4 + we * (r0 * r2);
    q[3] = (F10 * c01 + F11 * c11) * m4 + (we * (r1 * r1) + ww);
    q[4] = (F10 * c02 + F11 * c12) * m4 + we * (r1 * r2);
    q[5] = (F20 * c02 + F21 * c12) * m4 + (we * (r2 * r2) + ww);
    v2d gr = vsplat(-2.0) * gw;
    v2d y[3];
    y[0] = (F00 * z0 + F01 * z1) * two + gr * r0;
    y[1] = (F10 * z0 + F11 * z1) * two + gr * r1;
    y[2] = (F20 * z0 + F21 * z1) * two + gr * r2;
    v2d out[WORK] = {t00, t01, t10, t11, t20, t21, c00, c01, c02, c10, c11, c12, z0, z1};
    for (int k = 0; k < WORK; k++) {
        if (lanes == 2)
            memcpy(work + k * n + j, &out[k], sizeof out[k]);
        else
            work[k * n + j] = out[k][0];
    }
    if (lanes == 1) {  /* drop lane 1's copy of the sample from the sums (a select: inf·0 is NaN) */
        const v2l lane0 = {-1, 0};
        for (int k = 0; k < 6; k++)
            q[k] = vselect(lane0, q[k], vsplat(0.0));
        for (int k = 0; k < 3; k++)
            y[k] = vselect(lane0, y[k], vsplat(0.0));
    }
    v2d xb[4] = {x0, x1, x2, one};
    int pair = 0;
    for (int c = 0; c < 4; c++) {
        for (int d = c; d < 4; d++, pair++) {
            v2d xx = xb[c] * xb[d];
            for (int k = 0; k < 6; k++)
                acc[6 * pair + k] += xx * q[k];
        }
        for (int k = 0; k < 3; k++)
            acc[60 + 3 * c + k] += xb[c] * y[k];
    }
}

static PyObject *lm_reduce(PyObject *self, PyObject *args)
{
    PyObject *o_m, *o_x, *o_K, *o_b, *o_work, *o_acc;
    int kid;
    double t2, lam;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OOOOniddOO", &o_m, &o_x, &o_K, &o_b, &n, &kid, &t2, &lam,
                          &o_work, &o_acc))
        return NULL;
    buf_t bufs[6];
    memset(bufs, 0, sizeof bufs);
    if (check_n_kid(n, kid) || get_doubles(o_m, &bufs[0], 3, n, 0, "m")
        || get_doubles(o_x, &bufs[1], 3, n, 0, "x") || get_doubles(o_K, &bufs[2], 3, 3, 0, "K")
        || get_doubles(o_b, &bufs[3], 3, -1, 0, "b") || get_doubles(o_work, &bufs[4], WORK, n, 1, "work")
        || get_doubles(o_acc, &bufs[5], 72, -1, 1, "acc")) {
        release(bufs, 6);
        return NULL;
    }
    const double *m = bufs[0].view.buf, *x = bufs[1].view.buf, *K = bufs[2].view.buf,
                 *b = bufs[3].view.buf;
    double *work = bufs[4].view.buf, *out = bufs[5].view.buf;
    Py_BEGIN_ALLOW_THREADS
    v2d acc[72];
    for (int k = 0; k < 72; k++)
        acc[k] = vsplat(0.0);
    Py_ssize_t j = 0;
    for (; j + 1 < n; j += 2)
        reduce_pair(m, x, K, b, n, j, 2, kid, t2, lam, work, acc);
    if (j < n)
        reduce_pair(m, x, K, b, n, j, 1, kid, t2, lam, work, acc);
    for (int k = 0; k < 72; k++)
        out[k] = acc[k][0] + acc[k][1];
    Py_END_ALLOW_THREADS
    release(bufs, 6);
    Py_RETURN_NONE;
}

static PyObject *lm_step(PyObject *self, PyObject *args)
{
    PyObject *o_x, *o_work, *o_full, *o_out;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OnOOO", &o_x, &n, &o_work, &o_full, &o_out))
        return NULL;
    buf_t bufs[4];
    memset(bufs, 0, sizeof bufs);
    if (check_n_kid(n, KERNEL_CAUCHY) || get_doubles(o_x, &bufs[0], 3, n, 0, "x")
        || get_doubles(o_work, &bufs[1], WORK, n, 0, "work")
        || get_doubles(o_full, &bufs[2], 12, -1, 0, "full")
        || get_doubles(o_out, &bufs[3], 3, n, 1, "out")) {
        release(bufs, 4);
        return NULL;
    }
    const double *x = bufs[0].view.buf, *work = bufs[1].view.buf, *full = bufs[2].view.buf;
    double *out = bufs[3].view.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++) {
        double x0 = x[j], x1 = x[n + j], x2 = x[2 * n + j];
        const double *wk = work + j;
        /* J_p Δp = ΔK x + Δb (full[3c + a] = ΔK[a, c], full[9 + a] = Δb[a]), Δt = 2 C (J_p Δp)
         * + z, Δx = −T Δt, then back onto the sphere */
        double j0 = full[0] * x0 + full[3] * x1 + full[6] * x2 + full[9];
        double j1 = full[1] * x0 + full[4] * x1 + full[7] * x2 + full[10];
        double j2 = full[2] * x0 + full[5] * x1 + full[8] * x2 + full[11];
        double dt0 = (wk[6 * n] * j0 + wk[7 * n] * j1 + wk[8 * n] * j2) * 2.0 + wk[12 * n];
        double dt1 = (wk[9 * n] * j0 + wk[10 * n] * j1 + wk[11 * n] * j2) * 2.0 + wk[13 * n];
        double v0 = x0 - (wk[0] * dt0 + wk[1 * n] * dt1);
        double v1 = x1 - (wk[2 * n] * dt0 + wk[3 * n] * dt1);
        double v2 = x2 - (wk[4 * n] * dt0 + wk[5 * n] * dt1);
        double norm = sqrt(v0 * v0 + v1 * v1 + v2 * v2);
        out[j] = v0 / norm;
        out[n + j] = v1 / norm;
        out[2 * n + j] = v2 / norm;
    }
    Py_END_ALLOW_THREADS
    release(bufs, 4);
    Py_RETURN_NONE;
}

static PyObject *lm_residuals(PyObject *self, PyObject *args)
{
    PyObject *o_m, *o_x, *o_K, *o_b, *o_r, *o_norm, *o_weight;
    int kid;
    double t2;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OOOOnidOOO", &o_m, &o_x, &o_K, &o_b, &n, &kid, &t2, &o_r,
                          &o_norm, &o_weight))
        return NULL;
    buf_t bufs[7];
    memset(bufs, 0, sizeof bufs);
    if (check_n_kid(n, kid) || get_doubles(o_m, &bufs[0], 3, n, 0, "m")
        || get_doubles(o_x, &bufs[1], 3, n, 0, "x") || get_doubles(o_K, &bufs[2], 3, 3, 0, "K")
        || get_doubles(o_b, &bufs[3], 3, -1, 0, "b") || get_doubles(o_r, &bufs[4], n, 3, 1, "r")
        || get_doubles(o_norm, &bufs[5], n, -1, 1, "norm")
        || get_doubles(o_weight, &bufs[6], n, -1, 1, "weight")) {
        release(bufs, 7);
        return NULL;
    }
    const double *m = bufs[0].view.buf, *x = bufs[1].view.buf, *K = bufs[2].view.buf,
                 *b = bufs[3].view.buf;
    double *r = bufs[4].view.buf, *norm = bufs[5].view.buf, *weight = bufs[6].view.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++) {
        double *rj = r + 3 * j;
        residual(m, x, K, b, n, j, rj);
        double s = rj[0] * rj[0] + rj[1] * rj[1] + rj[2] * rj[2], d1, d2;
        derivatives(kid, t2, s, &d1, &d2);
        norm[j] = sqrt(s);
        weight[j] = d1;
    }
    Py_END_ALLOW_THREADS
    release(bufs, 7);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"cost", lm_cost, METH_VARARGS,
     "cost(m, x, K, b, n, kernel_id, tau2) -> Σ ρ(‖K x_j + b − m_j‖²)"},
    {"reduce", lm_reduce, METH_VARARGS,
     "reduce(m, x, K, b, n, kernel_id, tau2, lam, work, acc): the Schur system's per-sample sums"},
    {"step", lm_step, METH_VARARGS,
     "step(x, n, work, full, out): the directions after the global step, on the sphere"},
    {"residuals", lm_residuals, METH_VARARGS,
     "residuals(m, x, K, b, n, kernel_id, tau2, r, norm, weight): r (N,3), ‖r‖ and ρ′(‖r‖²)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_lmcore",
    "Compiled per-sample loops of the robust LM (streamcal.fitting.lm_compiled).", -1, methods,
};

static int add_float(PyObject *mod, const char *name, double value)
{
    PyObject *obj = PyFloat_FromDouble(value);
    int rc = PyModule_AddObjectRef(mod, name, obj);  /* -1 with the error set when obj is NULL */
    Py_XDECREF(obj);
    return rc;
}

PyMODINIT_FUNC PyInit__lmcore(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL)
        return NULL;
    /* the constants compiled in, for lm_compiled and the tests to hold against kernels.py */
    if (add_float(mod, "S_FLOOR", S_FLOOR) < 0 || add_float(mod, "D_MIN", D_MIN) < 0
        || PyModule_AddIntConstant(mod, "WORK", WORK) < 0
        || PyModule_AddIntConstant(mod, "KERNEL_CAUCHY", KERNEL_CAUCHY) < 0
        || PyModule_AddIntConstant(mod, "KERNEL_GM", KERNEL_GM) < 0
        || PyModule_AddStringConstant(mod, "SOURCE_SHA256", LMCORE_SOURCE_SHA256) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
