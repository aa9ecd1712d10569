/* The per-sample loops of stage 2's LM for the core model (K, b; no effect term) under the
 * default fit's kernels (Cauchy, Geman–McClure): the algebra of streamcal/fitting/lm_blocks.py
 * (tangent-plane direction blocks, Triggs weights multiplied out) in one pass per call, every
 * per-sample quantity in registers. Python side: streamcal/fitting/lm_compiled.py.
 *
 * Why C and not numpy: at N = 1000 numpy's ~85 calls per iteration cost more in call overhead
 * than in arithmetic; why C and not numba: numba's import costs ~0.5 s and ~100 MB per process,
 * more than a whole one-shot fit. Arrays come in through the buffer protocol (C-contiguous
 * float64), so no numpy headers are needed to build this.
 *
 * Layouts: m, x (3,N) rows x0.., x1.., x2..; K (3,3) row-major; b (3,); work (N,14) per sample
 * T (3,2) row-major, C = H_t⁻¹ Fᵀ (2,3) row-major, z = H_t⁻¹ gt (2,); acc (72,) = Σ x̄_c x̄_d Q
 * over the pairs c ≤ d of x̄ = [x; 1] (10 rows × Q's 6 unique entries), then Σ x̄_c y (4 × 3).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#define S_FLOOR 1e-12
#define D_MIN 0.25
#define WORK 14
#define KERNEL_CAUCHY 0
#define KERNEL_GM 1

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

/* The buffer of obj as `count` C-contiguous doubles (writable when asked), or an exception. */
static int get_doubles(PyObject *obj, buf_t *buf, Py_ssize_t count, int writable, const char *name)
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
    if (buf->view.len != count * (Py_ssize_t)sizeof(double)) {
        PyErr_Format(PyExc_ValueError, "%s holds %zd values, expected %zd", name,
                     buf->view.len / (Py_ssize_t)sizeof(double), count);
        return -1;
    }
    return 0;
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
    if (get_doubles(o_m, &bufs[0], 3 * n, 0, "m") || get_doubles(o_x, &bufs[1], 3 * n, 0, "x")
        || get_doubles(o_K, &bufs[2], 9, 0, "K") || get_doubles(o_b, &bufs[3], 3, 0, "b")) {
        release(bufs, 4);
        return NULL;
    }
    const double *m = bufs[0].view.buf, *x = bufs[1].view.buf, *K = bufs[2].view.buf,
                 *b = bufs[3].view.buf;
    double total = 0.0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++) {
        double x0 = x[j], x1 = x[n + j], x2 = x[2 * n + j];
        double r0 = (K[0] * x0 + K[1] * x1 + K[2] * x2) - m[j] + b[0];
        double r1 = (K[3] * x0 + K[4] * x1 + K[5] * x2) - m[n + j] + b[1];
        double r2 = (K[6] * x0 + K[7] * x1 + K[8] * x2) - m[2 * n + j] + b[2];
        double s = r0 * r0 + r1 * r1 + r2 * r2;
        total += kid == KERNEL_CAUCHY ? t2 * log1p(s / t2) : s * t2 / (t2 + s);
    }
    Py_END_ALLOW_THREADS
    release(bufs, 4);
    return PyFloat_FromDouble(total);
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
    if (get_doubles(o_m, &bufs[0], 3 * n, 0, "m") || get_doubles(o_x, &bufs[1], 3 * n, 0, "x")
        || get_doubles(o_K, &bufs[2], 9, 0, "K") || get_doubles(o_b, &bufs[3], 3, 0, "b")
        || get_doubles(o_work, &bufs[4], WORK * n, 1, "work")
        || get_doubles(o_acc, &bufs[5], 72, 1, "acc")) {
        release(bufs, 6);
        return NULL;
    }
    const double *m = bufs[0].view.buf, *x = bufs[1].view.buf, *K = bufs[2].view.buf,
                 *b = bufs[3].view.buf;
    double *work = bufs[4].view.buf, *out = bufs[5].view.buf;
    Py_BEGIN_ALLOW_THREADS
    double acc[72] = {0.0};
    for (Py_ssize_t j = 0; j < n; j++) {
        double x0 = x[j], x1 = x[n + j], x2 = x[2 * n + j];
        double r0 = (K[0] * x0 + K[1] * x1 + K[2] * x2) - m[j] + b[0];
        double r1 = (K[3] * x0 + K[4] * x1 + K[5] * x2) - m[n + j] + b[1];
        double r2 = (K[6] * x0 + K[7] * x1 + K[8] * x2) - m[2 * n + j] + b[2];
        double s = r0 * r0 + r1 * r1 + r2 * r2;
        double d1, d2;
        derivatives(kid, t2, s, &d1, &d2);
        /* Triggs weights (kernels.triggs_weights): W = w I + e r rᵀ, gradient scale gw */
        double w = d1 > 1e-300 ? d1 : 1e-300;
        double e, gw = w;
        if (s > S_FLOOR) {
            double clamp = (D_MIN - 1.0) * w / s;
            e = 2.0 * d2 > clamp ? 2.0 * d2 : clamp;
        } else {
            double D = 1.0 + 2.0 * s * d2 / w;
            e = 0.0;
            gw = w / sqrt(D > D_MIN ? D : D_MIN);
        }
        /* orthonormal tangent basis T (3,2) at x (Duff et al. 2017) */
        double sg = copysign(1.0, x2);
        double a = -1.0 / (sg + x2);
        double bb = x0 * x1 * a;
        double sx = sg * x0;
        double t00 = sx * x0 * a + 1.0, t01 = bb;
        double t10 = sg * bb, t11 = x1 * x1 * a + sg;
        double t20 = -sx, t21 = -x1;
        /* D = K T (3,2), Dᵀr, H_t = 2 Dᵀ W D + λI, F = W D */
        double D00 = K[0] * t00 + K[1] * t10 + K[2] * t20, D01 = K[0] * t01 + K[1] * t11 + K[2] * t21;
        double D10 = K[3] * t00 + K[4] * t10 + K[5] * t20, D11 = K[3] * t01 + K[4] * t11 + K[5] * t21;
        double D20 = K[6] * t00 + K[7] * t10 + K[8] * t20, D21 = K[6] * t01 + K[7] * t11 + K[8] * t21;
        double dr0 = D00 * r0 + D10 * r1 + D20 * r2, dr1 = D01 * r0 + D11 * r1 + D21 * r2;
        double h00 = (D00 * D00 + D10 * D10 + D20 * D20) * (2.0 * w) + (2.0 * e) * (dr0 * dr0) + lam;
        double h01 = (D00 * D01 + D10 * D11 + D20 * D21) * (2.0 * w) + (2.0 * e) * (dr0 * dr1);
        double h11 = (D01 * D01 + D11 * D11 + D21 * D21) * (2.0 * w) + (2.0 * e) * (dr1 * dr1) + lam;
        double er0 = e * r0, er1 = e * r1, er2 = e * r2;
        double F00 = w * D00 + er0 * dr0, F01 = w * D01 + er0 * dr1;
        double F10 = w * D10 + er1 * dr0, F11 = w * D11 + er1 * dr1;
        double F20 = w * D20 + er2 * dr0, F21 = w * D21 + er2 * dr1;
        double det = h00 * h11 - h01 * h01;
        double i00 = h11 / det, i01 = -h01 / det, i11 = h00 / det;
        /* C = H_t⁻¹ Fᵀ (2,3), z = H_t⁻¹ Tᵀ g_x */
        double c00 = i00 * F00 + i01 * F01, c01 = i00 * F10 + i01 * F11, c02 = i00 * F20 + i01 * F21;
        double c10 = i01 * F00 + i11 * F01, c11 = i01 * F10 + i11 * F11, c12 = i01 * F20 + i11 * F21;
        double g0 = (2.0 * gw) * dr0, g1 = (2.0 * gw) * dr1;
        double z0 = i00 * g0 + i01 * g1, z1 = i01 * g0 + i11 * g1;
        /* Q = 2W − 4 F C (unique entries), y = −2γ r + 2 F z */
        double we = 2.0 * e, ww = 2.0 * w;
        double q[6];
        q[0] = (F00 * c00 + F01 * c10) * -4.0 + (we * (r0 * r0) + ww);
        q[1] = (F00 * c01 + F01 * c11) * -4.0 + we * (r0 * r1);
        q[2] = (F00 * c02 + F01 * c12) * -4.0 + we * (r0 * r2);
        q[3] = (F10 * c01 + F11 * c11) * -4.0 + (we * (r1 * r1) + ww);
        q[4] = (F10 * c02 + F11 * c12) * -4.0 + we * (r1 * r2);
        q[5] = (F20 * c02 + F21 * c12) * -4.0 + (we * (r2 * r2) + ww);
        double gr = -2.0 * gw;
        double y0 = (F00 * z0 + F01 * z1) * 2.0 + gr * r0;
        double y1 = (F10 * z0 + F11 * z1) * 2.0 + gr * r1;
        double y2 = (F20 * z0 + F21 * z1) * 2.0 + gr * r2;
        double *wk = work + WORK * j;
        wk[0] = t00; wk[1] = t01; wk[2] = t10; wk[3] = t11; wk[4] = t20; wk[5] = t21;
        wk[6] = c00; wk[7] = c01; wk[8] = c02; wk[9] = c10; wk[10] = c11; wk[11] = c12;
        wk[12] = z0; wk[13] = z1;
        double xb[4] = {x0, x1, x2, 1.0};
        int pair = 0;
        for (int c = 0; c < 4; c++) {
            for (int d = c; d < 4; d++, pair++) {
                double xx = xb[c] * xb[d];
                for (int k = 0; k < 6; k++)
                    acc[6 * pair + k] += xx * q[k];
            }
            acc[60 + 3 * c] += xb[c] * y0;
            acc[61 + 3 * c] += xb[c] * y1;
            acc[62 + 3 * c] += xb[c] * y2;
        }
    }
    memcpy(out, acc, sizeof acc);
    Py_END_ALLOW_THREADS
    release(bufs, 6);
    Py_RETURN_NONE;
}

static PyObject *lm_step(PyObject *self, PyObject *args)
{
    PyObject *o_x, *o_work, *o_dK, *o_db, *o_out;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OnOOOO", &o_x, &n, &o_work, &o_dK, &o_db, &o_out))
        return NULL;
    buf_t bufs[5];
    memset(bufs, 0, sizeof bufs);
    if (get_doubles(o_x, &bufs[0], 3 * n, 0, "x") || get_doubles(o_work, &bufs[1], WORK * n, 0, "work")
        || get_doubles(o_dK, &bufs[2], 9, 0, "dK") || get_doubles(o_db, &bufs[3], 3, 0, "db")
        || get_doubles(o_out, &bufs[4], 3 * n, 1, "out")) {
        release(bufs, 5);
        return NULL;
    }
    const double *x = bufs[0].view.buf, *work = bufs[1].view.buf, *dK = bufs[2].view.buf,
                 *db = bufs[3].view.buf;
    double *out = bufs[4].view.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++) {
        double x0 = x[j], x1 = x[n + j], x2 = x[2 * n + j];
        const double *wk = work + WORK * j;
        /* J_p Δp = ΔK x + Δb, Δt = 2 C (J_p Δp) + z, Δx = −T Δt, then back onto the sphere */
        double j0 = dK[0] * x0 + dK[1] * x1 + dK[2] * x2 + db[0];
        double j1 = dK[3] * x0 + dK[4] * x1 + dK[5] * x2 + db[1];
        double j2 = dK[6] * x0 + dK[7] * x1 + dK[8] * x2 + db[2];
        double dt0 = (wk[6] * j0 + wk[7] * j1 + wk[8] * j2) * 2.0 + wk[12];
        double dt1 = (wk[9] * j0 + wk[10] * j1 + wk[11] * j2) * 2.0 + wk[13];
        double v0 = x0 - (wk[0] * dt0 + wk[1] * dt1);
        double v1 = x1 - (wk[2] * dt0 + wk[3] * dt1);
        double v2 = x2 - (wk[4] * dt0 + wk[5] * dt1);
        double norm = sqrt(v0 * v0 + v1 * v1 + v2 * v2);
        out[j] = v0 / norm;
        out[n + j] = v1 / norm;
        out[2 * n + j] = v2 / norm;
    }
    Py_END_ALLOW_THREADS
    release(bufs, 5);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"cost", lm_cost, METH_VARARGS,
     "cost(m, x, K, b, n, kernel_id, tau2) -> Σ ρ(‖K x_j + b − m_j‖²)"},
    {"reduce", lm_reduce, METH_VARARGS,
     "reduce(m, x, K, b, n, kernel_id, tau2, lam, work, acc): the Schur system's per-sample sums"},
    {"step", lm_step, METH_VARARGS,
     "step(x, n, work, dK, db, out): the directions after the global step, on the sphere"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_lmcore",
    "Compiled per-sample loops of the robust LM (streamcal.fitting.lm_compiled).", -1, methods,
};

PyMODINIT_FUNC PyInit__lmcore(void)
{
    return PyModule_Create(&module);
}
