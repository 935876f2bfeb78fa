/* Compiled evaluation step of the lattice planner (deft_gym/planner/lattice.py), its
 * resampling of predicted obstacles (`resample`) and their relevance test (`near`), and its
 * longitudinal profiles (`profiles`); see their comments below.
 *
 * `evaluate` is LatticePlanner._evaluate_numpy written as plain loops: the same float
 * operations in the same order, so its results are bit-identical to the numpy version (numpy's
 * pairwise summation, np.interp's formula, NaN-propagating maximum/minimum, stable argsort
 * with NaN last, argmin returning the first NaN). The test suite checks the two against each
 * other on recorded and on corrupted frames. Build flags keep IEEE semantics (no fast-math, no
 * FMA contraction); see setup.py.
 *
 * Arrays are C-contiguous float64 (numpy arrays, read through the buffer protocol):
 *   ref_s, ref_x, ref_y, ref_h, ref_k  (N,)    reference line samples, ascending s
 *   vlim                               (V,)    curvature speed limit on a 1 m grid
 *   sva                                (3,P,K) longitudinal profiles: s, v, a
 *   penalty                            (P,)
 *   lat_d                              (3,L,K) lateral profiles: d, d', d''
 *   target_d, static_cost, c_route     (L,)
 *   hyst                               (L,) or None
 *   walls                              (L,) or a float
 *   obs_xy (2,M,K), obs_cs (2,M*K), obs_lw (2,M*K), obs_reach2 (M,1) or all None
 *   tk                                 (K,)
 *   params                             (N_PARAMS,) see enum below
 * Returns (lateral index, longitudinal index, cost); (-1, -1, inf) when nothing is feasible.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

enum { /* per call: desired speed, reference line and lateral options; then planner constants
        * (LatticePlanner._kernel_params fills them in this order) */
    P_V_DES, P_S_FIRST, P_VLIM_MIN, P_VLIM_MAX, P_BAND_LO, P_BAND_HI, P_W_LAT,
    P_W_SPEED_K, P_W_ACC, P_W_JERK, P_EGO_W2, P_EDGE, P_HARD_LAT, P_W_LAT_ACC, P_W_OBS, P_SOFT,
    P_LA, P_WA, P_LH, P_WH, P_TAN_HEAD, P_LAT_SLACK, P_BATCH, N_PARAMS
};

/* np.maximum / np.minimum on two doubles: NaN in either propagates, and of two equal values
 * the second is returned (what numpy gives on x86, MAXPD/MINPD's rule: max(+0, -0) is -0) */
static inline double npmax(double a, double b) { return (a > b || isnan(a)) ? a : b; }
static inline double npmin(double a, double b) { return (a < b || isnan(a)) ? a : b; }

/* numpy's pairwise summation of n <= 128 contiguous doubles (what .sum(axis=-1) does per row) */
static double pairwise_sum(const double *a, Py_ssize_t n)
{
    if (n < 8) {
        double res = 0.0;
        for (Py_ssize_t i = 0; i < n; i++) res += a[i];
        return res;
    }
    if (n > 128) { /* numpy splits larger blocks in halves (multiples of 8) */
        Py_ssize_t n2 = n / 2;
        n2 -= n2 % 8;
        return pairwise_sum(a, n2) + pairwise_sum(a + n2, n - n2);
    }
    double r[8];
    for (int j = 0; j < 8; j++) r[j] = a[j];
    Py_ssize_t i;
    for (i = 8; i < n - (n % 8); i += 8)
        for (int j = 0; j < 8; j++) r[j] += a[i + j];
    double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
    for (; i < n; i++) res += a[i];
    return res;
}

/* sum of squares of a row (numpy: (x * x).sum(axis=-1)) */
static double sum_sq(const double *x, Py_ssize_t n, double *tmp)
{
    for (Py_ssize_t i = 0; i < n; i++) tmp[i] = x[i] * x[i];
    return pairwise_sum(tmp, n);
}

/* np.interp on ascending xp: the bracketing index (-1 below, n above), found from a guess */
typedef struct {
    const double *xp;
    Py_ssize_t n;
    double x0, inv_step; /* a uniform-grid guess; exactness comes from the bracket checks */
} Grid;

static Py_ssize_t grid_index(const Grid *g, double x)
{
    const double *xp = g->xp;
    Py_ssize_t n = g->n;
    if (x < xp[0]) return -1;
    if (x > xp[n - 1]) return n;
    double f = (x - g->x0) * g->inv_step;
    Py_ssize_t j = (f > 0.0 && f < (double)n) ? (Py_ssize_t)f : 0;
    if (j > n - 1) j = n - 1;
    while (j > 0 && xp[j] > x) j--;
    while (j < n - 1 && xp[j + 1] <= x) j++;
    return j;
}

static inline double interp_at(const Grid *g, Py_ssize_t j, double x, const double *fp)
{
    Py_ssize_t n = g->n;
    const double *xp = g->xp;
    if (j < 0) return fp[0];
    if (j >= n) return fp[n - 1];
    if (j == n - 1) return fp[j];
    if (xp[j] == x) return fp[j];
    double slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]);
    double r = slope * (x - xp[j]) + fp[j];
    if (isnan(r)) {
        r = slope * (x - xp[j + 1]) + fp[j + 1];
        if (isnan(r) && fp[j] == fp[j + 1]) r = fp[j];
    }
    return r;
}

static inline double interp1(const Grid *g, double x, const double *fp)
{
    if (isnan(x)) return x;
    return interp_at(g, grid_index(g, x), x, fp);
}

/* (x, y) and heading (reference + relative) of the ego along one candidate row */
typedef struct {
    const Grid *g;
    const double *rx, *ry, *rh, *rk;
} Ref;

static void row_poses(const Ref *ref, const double *s, const double *v, const double *kr,
                      const double *d, const double *dd, Py_ssize_t K, double *x, double *y,
                      double *eh)
{
    for (Py_ssize_t k = 0; k < K; k++) {
        double sk = s[k];
        double hr, xr, yr;
        if (isnan(sk)) {
            hr = xr = yr = sk;
        } else {
            Py_ssize_t j = grid_index(ref->g, sk);
            hr = interp_at(ref->g, j, sk, ref->rh);
            xr = interp_at(ref->g, j, sk, ref->rx);
            yr = interp_at(ref->g, j, sk, ref->ry);
        }
        x[k] = xr - d[k] * sin(hr);
        y[k] = yr + d[k] * cos(hr);
        double vs = v[k] * (1.0 - kr[k] * d[k]);
        eh[k] = hr + atan2(dd[k], npmax(vs, 1e-3));
    }
}

/* separating-axis test (lattice._box_separation) of one pair: separation and the same for the
 * ego box grown by (lh, wh) */
typedef struct {
    double la, wa, lh, wh;
} Ego;

static inline void box_separation(double dx, double dy, double ec, double es, double oc,
                                  double os, double lb, double wb, const Ego *e, double *sep,
                                  double *sep_h)
{
    double rel0 = fabs(oc * ec + os * es);
    double rel1 = fabs(os * ec + (-oc) * es);
    double q1 = fabs(dx * ec + dy * es) - (lb * rel0 + wb * rel1) - e->la;
    double q2 = fabs(dy * ec + (-dx) * es) - (lb * rel1 + wb * rel0) - e->wa;
    double q3 = fabs(dx * oc + dy * os) - lb - (e->la * rel0 + e->wa * rel1);
    double q4 = fabs(dy * oc + (-dx) * os) - wb - (e->la * rel1 + e->wa * rel0);
    *sep = npmax(npmax(q1, q2), npmax(q3, q4));
    double h1 = q1 - e->lh, h2 = q2 - e->wh;
    double h3 = q3 - (e->lh * rel0 + e->wh * rel1);
    double h4 = q4 - (e->lh * rel1 + e->wh * rel0);
    *sep_h = npmax(npmax(h1, h2), npmax(h3, h4));
}

/* np.clip(x.astype(np.int64), 0, n - 1) for one x: truncation; NaN, infinities and values
 * beyond int64 become INT64_MIN (x86's conversion result), clipped to 0 */
static inline Py_ssize_t vlim_index(double x, Py_ssize_t n)
{
    if (!(x > -9223372036854775808.0 && x < 9223372036854775808.0)) return 0;
    int64_t t = (int64_t)x;
    return t < 0 ? 0 : (t > n - 1 ? n - 1 : (Py_ssize_t)t);
}

/* stable argsort with NaN last: sort (value, index) pairs */
typedef struct {
    double v;
    Py_ssize_t i;
} Key;

static int key_cmp(const void *pa, const void *pb)
{
    const Key *a = pa, *b = pb;
    int na = isnan(a->v), nb = isnan(b->v);
    if (na != nb) return na - nb;
    if (!na) {
        if (a->v < b->v) return -1;
        if (a->v > b->v) return 1;
    }
    return (a->i > b->i) - (a->i < b->i);
}

/* -- argument handling ---------------------------------------------------------------------- */
#define MAX_BUF 20
typedef struct {
    Py_buffer b[MAX_BUF];
    int n;
} Buffers;

static double *get_array_flags(Buffers *bs, PyObject *o, int ndim, Py_ssize_t *shape,
                                const char *name, int flags)
{
    if (bs->n >= MAX_BUF) {
        PyErr_SetString(PyExc_RuntimeError, "more arrays than MAX_BUF");
        return NULL;
    }
    Py_buffer *v = &bs->b[bs->n];
    if (PyObject_GetBuffer(o, v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | flags) < 0) return NULL;
    bs->n++;
    if (v->itemsize != 8 || strcmp(v->format, "d") != 0 || v->ndim != ndim) {
        PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous float64 array of %d dimensions",
                     name, ndim);
        return NULL;
    }
    for (int i = 0; i < ndim; i++) {
        if (shape[i] < 0) shape[i] = v->shape[i];
        else if (shape[i] != v->shape[i]) {
            PyErr_Format(PyExc_ValueError, "%s: dimension %d is %zd, expected %zd", name, i,
                         v->shape[i], shape[i]);
            return NULL;
        }
    }
    return (double *)v->buf;
}

static const double *get_array(Buffers *bs, PyObject *o, int ndim, Py_ssize_t *shape,
                               const char *name)
{
    return get_array_flags(bs, o, ndim, shape, name, 0);
}

static void release(Buffers *bs)
{
    for (int i = 0; i < bs->n; i++) PyBuffer_Release(&bs->b[i]);
    bs->n = 0;
}

/* the obstacle cost of one candidate row (lattice._obstacle_cost for one row) */
typedef struct {
    const Ref *ref;
    const double *sva, *lat_d, *kr;
    const double *oxy, *ocs, *olw, *reach2;
    Py_ssize_t L, P, K, M;
    Ego ego;
    double w_obs, soft;
    double *x, *y, *eh; /* (K,) scratch */
} Obstacles;

static void row_arrays(const Obstacles *o, Py_ssize_t r, const double **s, const double **v,
                       const double **kr, const double **d, const double **dd)
{
    Py_ssize_t li = r / o->P, pi = r % o->P, K = o->K;
    *s = o->sva + pi * K;
    *v = o->sva + (o->P + pi) * K;
    *kr = o->kr + pi * K;
    *d = o->lat_d + li * K;
    *dd = o->lat_d + (o->L + li) * K;
}

/* sep_h at the start pose of row r (time 0) against every obstacle at time 0 */
static void start_sep(const Obstacles *o, Py_ssize_t r, double *sep_h0)
{
    const double *s, *v, *kr, *d, *dd;
    row_arrays(o, r, &s, &v, &kr, &d, &dd);
    double x, y, eh;
    row_poses(o->ref, s, v, kr, d, dd, 1, &x, &y, &eh);
    double ec = cos(eh), es = sin(eh);
    Py_ssize_t M = o->M, K = o->K, MK = M * K;
    for (Py_ssize_t m = 0; m < M; m++) {
        double sep;
        Py_ssize_t f = m * K;
        box_separation(o->oxy[f] - x, o->oxy[MK + f] - y, ec, es, o->ocs[f], o->ocs[MK + f],
                       o->olw[f], o->olw[MK + f], &o->ego, &sep, &sep_h0[m]);
    }
}

static double row_cost(const Obstacles *o, Py_ssize_t r, const double *sep_h0)
{
    const double *s, *v, *kr, *d, *dd;
    row_arrays(o, r, &s, &v, &kr, &d, &dd);
    Py_ssize_t K = o->K, M = o->M, MK = M * K;
    row_poses(o->ref, s, v, kr, d, dd, K, o->x, o->y, o->eh);
    double acc = 0.0;
    int close = 0, bad = 0;
    for (Py_ssize_t m = 0; m < M; m++) {
        double reach2 = o->reach2[m];
        double lim = npmin(0.0, sep_h0[m] - 0.05);
        for (Py_ssize_t k = 0; k < K; k++) {
            Py_ssize_t f = m * K + k;
            double dx = o->oxy[f] - o->x[k], dy = o->oxy[MK + f] - o->y[k];
            if (!(dx * dx + dy * dy < reach2)) continue;
            close = 1;
            double sep, sep_h;
            box_separation(dx, dy, cos(o->eh[k]), sin(o->eh[k]), o->ocs[f], o->ocs[MK + f],
                           o->olw[f], o->olw[MK + f], &o->ego, &sep, &sep_h);
            if (sep < 0.0 || sep_h < lim) bad = 1;
            acc += npmax(o->soft - npmax(sep, 0.0), 0.0);
        }
    }
    if (!close) return 0.0;
    return bad ? INFINITY : o->w_obs * acc;
}

static PyObject *evaluate(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 20) {
        PyErr_Format(PyExc_TypeError, "evaluate() takes 20 arguments (%zd given)", nargs);
        return NULL;
    }
    Buffers bs = {.n = 0};
    PyObject *result = NULL;
    double *work = NULL;
    Key *keys = NULL;
    Py_ssize_t N = -1, V = -1, P = -1, K = -1, L = -1, M = -1, NP = N_PARAMS;
    Py_ssize_t sh3[3], sh2[2], sh1[1];
#define ARR1(var, idx, n_, name)                                                         \
    sh1[0] = n_;                                                                         \
    const double *var = get_array(&bs, args[idx], 1, sh1, name);                         \
    if (!var) goto done;                                                                 \
    n_ = sh1[0];
    ARR1(ref_s, 0, N, "ref_s")
    ARR1(ref_x, 1, N, "ref_x")
    ARR1(ref_y, 2, N, "ref_y")
    ARR1(ref_h, 3, N, "ref_h")
    ARR1(ref_k, 4, N, "ref_k")
    ARR1(vlim, 5, V, "vlim")
    sh3[0] = 3; sh3[1] = -1; sh3[2] = -1;
    const double *sva = get_array(&bs, args[6], 3, sh3, "sva");
    if (!sva) goto done;
    P = sh3[1]; K = sh3[2];
    ARR1(penalty, 7, P, "penalty")
    sh3[0] = 3; sh3[1] = -1; sh3[2] = K;
    const double *lat_d = get_array(&bs, args[8], 3, sh3, "lat_d");
    if (!lat_d) goto done;
    L = sh3[1];
    ARR1(target_d, 9, L, "target_d")
    ARR1(static_cost, 10, L, "static_cost")
    ARR1(c_route, 11, L, "c_route")
    const double *hyst = NULL;
    if (args[12] != Py_None) {
        ARR1(hyst_, 12, L, "hyst")
        hyst = hyst_;
    }
    const double *walls = NULL;
    double wall_all = 0.0;
    if (PyFloat_Check(args[13])) {
        wall_all = PyFloat_AS_DOUBLE(args[13]);
    } else {
        ARR1(walls_, 13, L, "walls")
        walls = walls_;
    }
    const double *oxy = NULL, *ocs = NULL, *olw = NULL, *reach2 = NULL;
    if (args[14] != Py_None) {
        sh3[0] = 2; sh3[1] = -1; sh3[2] = K;
        oxy = get_array(&bs, args[14], 3, sh3, "obs_xy");
        if (!oxy) goto done;
        M = sh3[1];
        Py_ssize_t MK = M * K;
        sh2[0] = 2; sh2[1] = MK;
        if (!(ocs = get_array(&bs, args[15], 2, sh2, "obs_cs"))) goto done;
        if (!(olw = get_array(&bs, args[16], 2, sh2, "obs_lw"))) goto done;
        sh2[0] = M; sh2[1] = 1;
        if (!(reach2 = get_array(&bs, args[17], 2, sh2, "obs_reach2"))) goto done;
    }
    ARR1(tk, 18, K, "tk")
    ARR1(prm, 19, NP, "params")
    if (N < 2 || V < 1 || P < 1 || K < 2 || L < 1) {
        PyErr_SetString(PyExc_ValueError, "evaluate: empty reference line, profiles or options");
        goto done;
    }

    Grid grid = {ref_s, N, ref_s[0], 1.0 / (ref_s[1] - ref_s[0])};
    Ref ref = {&grid, ref_x, ref_y, ref_h, ref_k};
    const double *ls = sva, *lv = sva + P * K, *la = sva + 2 * P * K;
    const double *d = lat_d, *ddd = lat_d + 2 * L * K;
    Py_ssize_t LP = L * P;
    /* scratch: kr (P K), c_lon, ok_lon, ls_max (P), c_lat, ok_lat (L), base (L P), tmp, x, y,
     * eh (K), sep_h0 (M) */
    Py_ssize_t n_work = P * K + 3 * P + 2 * L + LP + 4 * K + (M > 0 ? M : 0);
    work = PyMem_Malloc(sizeof(double) * (size_t)n_work);
    keys = PyMem_Malloc(sizeof(Key) * (size_t)LP);
    if (!work || !keys) {
        PyErr_NoMemory();
        goto done;
    }
    double *kr = work, *c_lon = kr + P * K, *ok_lon = c_lon + P, *ls_max = ok_lon + P;
    double *c_lat = ls_max + P, *ok_lat = c_lat + L, *base = ok_lat + L, *tmp = base + LP;
    double *px = tmp + K, *py = px + K, *peh = py + K, *sep_h0 = peh + K;

    /* longitudinal-only: curvature, cost, speed limits */
    double v_des = prm[P_V_DES];
    double vref = v_des;
    if (1.0 > vref) vref = 1.0; /* Python's max(v_des, 1.0) */
    double c_speed = prm[P_W_SPEED_K] / pow(vref, 2.0);
    int uniform = prm[P_VLIM_MIN] == prm[P_VLIM_MAX];
    double s_first = prm[P_S_FIRST];
    double limit_all = prm[P_VLIM_MIN] + 0.3;
    for (Py_ssize_t i = 0; i < P * K; i++) kr[i] = interp1(&grid, ls[i], ref_k);
#define VLIM_AT(sv) (vlim[vlim_index((sv) - s_first, V)] + 0.3)
    int high = uniform ? (lv[0] > limit_all) : (lv[0] > VLIM_AT(ls[0]));
    for (Py_ssize_t p = 0; p < P; p++) {
        const double *s = ls + p * K, *v = lv + p * K, *a = la + p * K;
        for (Py_ssize_t k = 0; k < K; k++) tmp[k] = v[k] - v_des;
        double s_dv = sum_sq(tmp, K, tmp);
        double s_a = sum_sq(a, K, tmp);
        for (Py_ssize_t k = 0; k < K - 1; k++) tmp[k] = a[k + 1] - a[k];
        double s_j = sum_sq(tmp, K - 1, tmp);
        c_lon[p] = c_speed * s_dv + prm[P_W_ACC] * s_a + prm[P_W_JERK] * s_j + penalty[p];
        int ok = 1;
        double smax = s[0];
        for (Py_ssize_t k = 0; k < K; k++) {
            double lim = uniform ? limit_all : VLIM_AT(s[k]);
            if (high) lim = npmax(lim, v[0] - 3.0 * tk[k]);
            if (!(v[k] > -0.1 && v[k] <= lim)) ok = 0;
            smax = npmax(smax, s[k]);
        }
        ok_lon[p] = ok;
        ls_max[p] = smax;
    }
#undef VLIM_AT
    /* lateral-only: drivable band and cost */
    for (Py_ssize_t l = 0; l < L; l++) {
        const double *dl = d + l * K;
        int ok = 1;
        double out0 = 0.0;
        for (Py_ssize_t k = 0; k < K; k++) {
            double t = ((dl[k] + prm[P_EGO_W2]) - prm[P_BAND_HI]) - prm[P_EDGE];
            double out = npmax(prm[P_BAND_LO] - dl[k], 0.0) + npmax(t, 0.0);
            if (k == 0) out0 = out + 0.05;
            if (!(out <= out0)) ok = 0;
            tmp[k] = dl[k] - target_d[l];
        }
        ok_lat[l] = ok;
        double c = prm[P_W_LAT] * sum_sq(tmp, K, tmp) + static_cost[l] + c_route[l];
        c_lat[l] = hyst ? c + hyst[l] : c;
    }
    /* pairs: walls and lateral acceleration, then the base cost */
    Py_ssize_t n_ok = 0;
    for (Py_ssize_t l = 0; l < L; l++) {
        const double *dd2 = ddd + l * K, *dl = d + l * K;
        double wall = (walls ? walls[l] : wall_all) + 0.05;
        for (Py_ssize_t p = 0; p < P; p++) {
            const double *krp = kr + p * K, *v = lv + p * K, *sp = ls + p * K;
            double amax = 0.0;
            int head = 1;
            for (Py_ssize_t k = 0; k < K; k++) {
                double a_k = fabs(krp[k] * v[k] * v[k] + dd2[k]);
                amax = k ? npmax(amax, a_k) : a_k;
                if (!(fabs(dl[k] - dl[0]) <= prm[P_TAN_HEAD] * (sp[k] - sp[0]) + prm[P_LAT_SLACK])) head = 0;
            }
            int feasible = (ls_max[p] <= wall) && (amax <= prm[P_HARD_LAT]) && ok_lon[p] != 0.0 &&
                           ok_lat[l] != 0.0 && head;
            double b = feasible ? (c_lat[l] + c_lon[p]) + prm[P_W_LAT_ACC] * amax : INFINITY;
            Py_ssize_t i = l * P + p;
            base[i] = b;
            keys[i].v = b;
            keys[i].i = i;
            if (isfinite(b)) n_ok++;
        }
    }
    if (n_ok == 0) {
        result = Py_BuildValue("nnd", (Py_ssize_t)-1, (Py_ssize_t)-1, INFINITY);
        goto done;
    }
    qsort(keys, (size_t)LP, sizeof(Key), key_cmp);
    if (!oxy) {
        Py_ssize_t i = keys[0].i;
        result = Py_BuildValue("nnd", i / P, i % P, base[i]);
        goto done;
    }
    /* the obstacle check, lazily in cost order (see _evaluate_numpy: chunks of 8, 32, 128, ...
     * pairs, judged in batches of 8; the start pose of a chunk's first pair sets the hard
     * buffer the ego may already be inside) */
    Obstacles ob = {&ref, sva, lat_d, kr, oxy, ocs, olw, reach2, L, P, K, M,
                    {prm[P_LA], prm[P_WA], prm[P_LH], prm[P_WH]}, prm[P_W_OBS], prm[P_SOFT],
                    px, py, peh};
    Py_ssize_t B = (Py_ssize_t)prm[P_BATCH];
    Py_ssize_t best_i = -1, start = 0, size = B;
    double best_cost = INFINITY;
    while (start < n_ok && base[keys[start].i] < best_cost) {
        Py_ssize_t end = start + size < n_ok ? start + size : n_ok;
        start_sep(&ob, keys[start].i, sep_h0);
        int stop = 0;
        for (Py_ssize_t b = start; b < end; b += B) {
            if (b != start && base[keys[b].i] >= best_cost) {
                stop = 1;
                break;
            }
            Py_ssize_t bend = b + B < end ? b + B : end, jm = -1;
            double tm = 0.0;
            for (Py_ssize_t q = b; q < bend; q++) { /* argmin: first minimum, or first NaN */
                Py_ssize_t i = keys[q].i;
                double t = base[i] + row_cost(&ob, i, sep_h0);
                if (jm < 0 || t < tm || (isnan(t) && !isnan(tm))) {
                    jm = q;
                    tm = t;
                }
                if (isnan(t)) break;
            }
            if (tm < best_cost) {
                best_i = keys[jm].i;
                best_cost = tm;
            }
        }
        if (stop) break;
        start += size;
        size *= 4;
    }
    if (best_i < 0) result = Py_BuildValue("nnd", (Py_ssize_t)-1, (Py_ssize_t)-1, INFINITY);
    else result = Py_BuildValue("nnd", best_i / P, best_i % P, best_cost);
#undef ARR1
done:
    release(&bs);
    PyMem_Free(work);
    PyMem_Free(keys);
    return result;
}


/* -- predicted obstacles at the planning times (lattice._obstacles, one group) ------------- */
static PyObject *KEY_X, *KEY_Y, *KEY_HEADING, *KEY_LENGTH, *KEY_WIDTH, *KEY_V;

/* the doubles of a list of exactly m Python floats (no ints, no bools), or NULL */
static PyObject *float_list(PyObject *ob, PyObject *key, Py_ssize_t m)
{
    PyObject *l = PyDict_GetItemWithError(ob, key);
    if (!l || !PyList_CheckExact(l) || PyList_GET_SIZE(l) != m) return NULL;
    for (Py_ssize_t i = 0; i < m; i++)
        if (!PyFloat_CheckExact(PyList_GET_ITEM(l, i))) return NULL;
    return l;
}

static int float_item(PyObject *ob, PyObject *key, int optional, double *out)
{
    PyObject *v = PyDict_GetItemWithError(ob, key);
    if (!v) {
        if (PyErr_Occurred() || !optional) return 0;
        *out = 0.0;
        return 1;
    }
    if (!PyFloat_CheckExact(v)) return 0;
    *out = PyFloat_AS_DOUBLE(v);
    return 1;
}

#define AT(l, i) PyFloat_AS_DOUBLE(PyList_GET_ITEM(l, i))

/* resample(obs, tq, ot0, inv_dt, m, j, oxy, oh, dims) -> bool
 *
 * The moving obstacles `obs` (dicts sharing the time base t0 = ot0, dt = 1 / inv_dt and m
 * prediction points) at the planning times `tq` (K,), written to rows j.. of oxy (2,N,K),
 * oh (N,K) and dims (N,3), as _obstacles' numpy lines do: linear interpolation of x and y,
 * heading of the nearest point (round half to even), held at both ends; half length, half width,
 * speed. Returns False, having maybe written part of those rows, when the input is not the
 * well-formed case (an obstacle that is not a dict, a value that is not a Python float, a list
 * of another length, a NaN time): the numpy lines then run and raise or compute what they do. */
static PyObject *resample(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError, "resample: expected 9 arguments");
        return NULL;
    }
    PyObject *obs = args[0];
    double ot0 = PyFloat_AsDouble(args[2]), inv = PyFloat_AsDouble(args[3]);
    Py_ssize_t m = PyLong_AsSsize_t(args[4]), j = PyLong_AsSsize_t(args[5]);
    if (PyErr_Occurred()) return NULL;
    if (!PyList_CheckExact(obs)) {
        PyErr_SetString(PyExc_TypeError, "resample: obs must be a list");
        return NULL;
    }
    Buffers bs = {.n = 0};
    PyObject *result = NULL;
    Py_ssize_t K = -1, N = -1;
    Py_ssize_t sh_tq[1] = {-1};
    const double *tq = get_array(&bs, args[1], 1, sh_tq, "tq");
    if (!tq) goto done;
    K = sh_tq[0];
    Py_ssize_t sh_xy[3] = {2, -1, K};
    double *oxy = get_array_flags(&bs, args[6], 3, sh_xy, "oxy", PyBUF_WRITABLE);
    if (!oxy) goto done;
    N = sh_xy[1];
    Py_ssize_t sh_h[2] = {N, K}, sh_d[2] = {N, 3};
    double *oh = get_array_flags(&bs, args[7], 2, sh_h, "oh", PyBUF_WRITABLE);
    double *dims = oh ? get_array_flags(&bs, args[8], 2, sh_d, "dims", PyBUF_WRITABLE) : NULL;
    if (!dims) goto done;
    Py_ssize_t n = PyList_GET_SIZE(obs);
    if (j < 0 || j + n > N || m < 2) {
        PyErr_SetString(PyExc_ValueError, "resample: rows out of range or fewer than 2 points");
        goto done;
    }
    result = Py_False;
    Py_ssize_t *i0 = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(2 * (K > 0 ? K : 1)));
    double *w = PyMem_Malloc(sizeof(double) * (size_t)(K > 0 ? K : 1));
    if (!i0 || !w) {
        PyMem_Free(i0);
        PyMem_Free(w);
        result = PyErr_NoMemory();
        goto done;
    }
    Py_ssize_t *ih = i0 + K;
    double last = (double)m - 1.0;
    for (Py_ssize_t k = 0; k < K; k++) {
        /* f = minimum(maximum((tq - t0) * (1 / dt), 0), m - 1); i = minimum(int64(f), m - 2) */
        double f = npmin(npmax((tq[k] - ot0) * inv, 0.0), last);
        if (isnan(f)) goto fallback;
        Py_ssize_t i = (Py_ssize_t)f;
        i0[k] = i < m - 2 ? i : m - 2;
        w[k] = f - (double)i0[k];
        ih[k] = (Py_ssize_t)nearbyint(f);
    }
    for (Py_ssize_t o = 0; o < n; o++) {
        PyObject *ob = PyList_GET_ITEM(obs, o);
        if (!PyDict_CheckExact(ob)) goto fallback;
        PyObject *X = float_list(ob, KEY_X, m), *Y = X ? float_list(ob, KEY_Y, m) : NULL;
        PyObject *H = Y ? float_list(ob, KEY_HEADING, m) : NULL;
        double len, wid, v;
        if (!H || !float_item(ob, KEY_LENGTH, 0, &len) || !float_item(ob, KEY_WIDTH, 0, &wid) ||
            !float_item(ob, KEY_V, 1, &v))
            goto fallback;
        double *rx = oxy + (j + o) * K, *ry = oxy + (N + j + o) * K, *rh = oh + (j + o) * K;
        for (Py_ssize_t k = 0; k < K; k++) {
            Py_ssize_t i = i0[k];
            double x0 = AT(X, i), y0 = AT(Y, i);
            rx[k] = x0 + (AT(X, i + 1) - x0) * w[k];
            ry[k] = y0 + (AT(Y, i + 1) - y0) * w[k];
            rh[k] = AT(H, ih[k]);
        }
        double *d = dims + (j + o) * 3;
        d[0] = 0.5 * len;
        d[1] = 0.5 * wid;
        d[2] = v;
    }
    result = Py_True;
fallback:
    PyMem_Free(i0);
    PyMem_Free(w);
    if (PyErr_Occurred()) result = NULL;
    else Py_INCREF(result);
done:
    release(&bs);
    return result;
}
#undef AT

/* -- longitudinal profiles (lattice._longitudinal's numpy lines and _brake) ------------------ */

/* the doubles of a list of exactly n Python floats, or NULL (nothing raised) */
static const double *float_seq(PyObject *l, Py_ssize_t n, double *out)
{
    if (!PyList_CheckExact(l) || PyList_GET_SIZE(l) != n) return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *v = PyList_GET_ITEM(l, i);
        if (!PyFloat_CheckExact(v)) return NULL;
        out[i] = PyFloat_AS_DOUBLE(v);
    }
    return out;
}

/* profiles(sva, cruise, reach, ti, ds, rv, s0, v0, a0, v_des, decel, tk) -> bool
 *
 * Fills sva (3,P,K) with s, v, a of the planner's longitudinal profiles, as _longitudinal's
 * numpy lines do, operation by operation:
 *   rows [0, C): cruise quartics, (v0 * cruise[0] + a0 * cruise[1]) + v_des * cruise[2]
 *                (cruise (3,3,C,K): speed, acceleration and desired-speed shapes), s + s0;
 *   rows [C, P-1): reach quintics of grid duration ti[r] (reach (T,4,3,K)),
 *                ((v0 * B0 + a0 * B1) + ds[r] * B2) + rv[r] * B3, s + s0;
 *   row P-1:     _brake(s0, v0, decel, tk).
 * Returns False, having written nothing that matters, when ti, ds, rv are not lists of
 * R = P - C - 1 in-range Python ints / Python floats: the numpy lines then run (and raise
 * what numpy raises). */
static PyObject *profiles(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 12) {
        PyErr_SetString(PyExc_TypeError, "profiles: expected 12 arguments");
        return NULL;
    }
    double s0 = PyFloat_AsDouble(args[6]), v0 = PyFloat_AsDouble(args[7]);
    double a0 = PyFloat_AsDouble(args[8]), v_des = PyFloat_AsDouble(args[9]);
    double decel = PyFloat_AsDouble(args[10]);
    if (PyErr_Occurred()) return NULL;
    Buffers bs = {.n = 0};
    PyObject *result = NULL;
    Py_ssize_t sh_tk[1] = {-1};
    const double *tk = get_array(&bs, args[11], 1, sh_tk, "tk");
    if (!tk) goto done;
    Py_ssize_t K = sh_tk[0];
    Py_ssize_t sh_sva[3] = {3, -1, K};
    double *sva = get_array_flags(&bs, args[0], 3, sh_sva, "sva", PyBUF_WRITABLE);
    if (!sva) goto done;
    Py_ssize_t P = sh_sva[1];
    Py_ssize_t sh_c[4] = {3, 3, -1, K}, sh_r[4] = {-1, 4, 3, K};
    const double *cruise = get_array(&bs, args[1], 4, sh_c, "cruise");
    const double *reach = cruise ? get_array(&bs, args[2], 4, sh_r, "reach") : NULL;
    if (!reach) goto done;
    Py_ssize_t C = sh_c[2], T = sh_r[0], R = P - C - 1;
    if (R < 0) {
        PyErr_SetString(PyExc_ValueError, "profiles: fewer rows than the cruise rows and the brake");
        goto done;
    }
    result = Py_False;
    double *coef = PyMem_Malloc(sizeof(double) * (size_t)(2 * R + 1));
    Py_ssize_t *ti = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(R + 1));
    if (!coef || !ti) {
        PyMem_Free(coef);
        PyMem_Free(ti);
        result = PyErr_NoMemory();
        goto done;
    }
    double *ds = coef, *rv = coef + R;
    if (!float_seq(args[4], R, ds) || !float_seq(args[5], R, rv) || !PyList_CheckExact(args[3]) ||
        PyList_GET_SIZE(args[3]) != R)
        goto fallback;
    for (Py_ssize_t r = 0; r < R; r++) {
        PyObject *v = PyList_GET_ITEM(args[3], r);
        if (!PyLong_CheckExact(v)) goto fallback;
        ti[r] = PyLong_AsSsize_t(v);
        if (ti[r] < 0 || ti[r] >= T) { /* numpy's take would raise (or wrap a negative index) */
            PyErr_Clear();
            goto fallback;
        }
    }
    const Py_ssize_t plane = P * K; /* s, v, a planes of sva */
    const Py_ssize_t cplane = C * K;
    for (int c = 0; c < 3; c++) {
        double *out = sva + c * plane;
        const double *bv = cruise + c * cplane, *ba = cruise + (3 + c) * cplane;
        const double *bf = cruise + (6 + c) * cplane;
        for (Py_ssize_t i = 0; i < cplane; i++) {
            double x = (v0 * bv[i] + a0 * ba[i]) + v_des * bf[i];
            out[i] = c == 0 ? x + s0 : x;
        }
        for (Py_ssize_t r = 0; r < R; r++) {
            const double *B = reach + ti[r] * 12 * K + c * K; /* B[ti, coefficient, c, :] */
            const double *B0 = B, *B1 = B + 3 * K, *B2 = B + 6 * K, *B3 = B + 9 * K;
            double *o = out + (C + r) * K;
            for (Py_ssize_t k = 0; k < K; k++) {
                double x = ((v0 * B0[k] + a0 * B1[k]) + ds[r] * B2[k]) + rv[r] * B3[k];
                o[k] = c == 0 ? x + s0 : x;
            }
        }
    }
    /* _brake: t_stop = max(v0, 0) / decel (Python's max: NaN v0 stays NaN) */
    double t_stop = (0.0 > v0 ? 0.0 : v0) / decel, half = 0.5 * decel;
    double *bs_ = sva + (P - 1) * K, *bv_ = bs_ + plane, *ba_ = bv_ + plane;
    for (Py_ssize_t k = 0; k < K; k++) {
        double tt = npmin(tk[k], t_stop);
        bs_[k] = (s0 + v0 * tt) - half * (tt * tt);
        bv_[k] = npmax(v0 - decel * tt, 0.0);
        ba_[k] = tk[k] < t_stop ? -decel : 0.0;
    }
    result = Py_True;
fallback:
    PyMem_Free(coef);
    PyMem_Free(ti);
    if (PyErr_Occurred()) result = NULL;
    else Py_INCREF(result);
done:
    release(&bs);
    return result;
}

/* near(oxy, ex, ey, reach2) -> list of bool
 *
 * Per obstacle row of oxy (2,N,K): whether its centre comes closer than sqrt(reach2) to
 * (ex, ey) at any time, as _obstacles' numpy line
 * ((gx * gx + gy * gy).min(axis=1) < reach2) with gx = x - ex, gy = y - ey: a NaN anywhere in
 * a row makes its minimum NaN, which is not near. */
static PyObject *near(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "near: expected 4 arguments");
        return NULL;
    }
    double ex = PyFloat_AsDouble(args[1]), ey = PyFloat_AsDouble(args[2]);
    double reach2 = PyFloat_AsDouble(args[3]);
    if (PyErr_Occurred()) return NULL;
    Buffers bs = {.n = 0};
    PyObject *result = NULL;
    Py_ssize_t sh[3] = {2, -1, -1};
    const double *oxy = get_array(&bs, args[0], 3, sh, "oxy");
    if (!oxy) goto done;
    Py_ssize_t N = sh[1], K = sh[2];
    if (K < 1) {
        PyErr_SetString(PyExc_ValueError, "near: no planning times");
        goto done;
    }
    result = PyList_New(N);
    if (!result) goto done;
    for (Py_ssize_t o = 0; o < N; o++) {
        const double *x = oxy + o * K, *y = oxy + (N + o) * K;
        double m = INFINITY;
        int nan = 0;
        for (Py_ssize_t k = 0; k < K; k++) {
            double gx = x[k] - ex, gy = y[k] - ey;
            double d2 = gx * gx + gy * gy;
            if (isnan(d2)) nan = 1;
            else if (d2 < m) m = d2;
        }
        PyObject *b = (!nan && m < reach2) ? Py_True : Py_False;
        Py_INCREF(b);
        PyList_SET_ITEM(result, o, b);
    }
done:
    release(&bs);
    return result;
}

static PyMethodDef methods[] = {
    {"evaluate", (PyCFunction)(void (*)(void))evaluate, METH_FASTCALL,
     "Cheapest feasible (lateral, longitudinal) pair and its cost; see the module source."},
    {"resample", (PyCFunction)(void (*)(void))resample, METH_FASTCALL,
     "Moving obstacles of one time base at the planning times; see the module source."},
    {"near", (PyCFunction)(void (*)(void))near, METH_FASTCALL,
     "Which predicted obstacles come within reach of a point; see the module source."},
    {"profiles", (PyCFunction)(void (*)(void))profiles, METH_FASTCALL,
     "The longitudinal profiles (cruise, reach, brake) into sva; see the module source."},
    {NULL, NULL, 0, NULL},
};

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
   "<digest of this file> <digest of the Python file it mirrors>"); the module that loads it
   refuses a build whose digests differ from the files beside it (a stale kernel) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_lattice_c",
                                    "Compiled evaluation step, obstacle resampling and profiles of the lattice planner.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__lattice_c(void)
{
    if (!(KEY_X = PyUnicode_InternFromString("x")) || !(KEY_Y = PyUnicode_InternFromString("y")) ||
        !(KEY_HEADING = PyUnicode_InternFromString("heading")) ||
        !(KEY_LENGTH = PyUnicode_InternFromString("length")) ||
        !(KEY_WIDTH = PyUnicode_InternFromString("width")) || !(KEY_V = PyUnicode_InternFromString("v")))
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) Py_CLEAR(m);
    return m;
}
