/* The epipolar matching cost (1 - ZNCC of patch descriptors) in one pass per lookup, eight lanes a vector
 * (simd8.h: AVX2 and FMA on x86-64, the same operations as vector extensions on other CPUs).
 *
 * Four kernels compute, number for number, what the package's torch code computes:
 * - frame_cost: the depth filter's cost against one frame, samples-first (S, R)
 *   (filter_search._frame_cost_torch): each row's own inverse depths, one frame, the cost set
 *   to inf where the frame does not see the sample;
 * - frame_search: the depth filter's whole search of a bucket of rows against one frame
 *   (filter_search._search_rows): frame_cost's costs on each row's grid of samples, the first
 *   minimum, the second-best ratio, the fine samples each side and the parabola, per row;
 * - filter_rows: all of a frame's searches of the filter's chosen rows (filter_frame_update:
 *   search_rows, the tests of each match, filter_first_check.check_first_matches): each row's
 *   span and bucket, frame_search's search of each bucket, the motion at the match, a bracket's
 *   edge test, the range, and every first measurement searched again at one sample a pixel;
 * - sweep_cost: the sweep's cost against n neighbours, rows-first (M, S)
 *   (cost_volume.sample_cost_torch): the neighbours' looked-up descriptors summed, then the
 *   ZNCC with the row's key descriptor, and the summed visibility returned as the count.
 * A lookup is grid_sample's (bilinear, zero padding, align_corners) of the descriptors at the
 * point a + rho b projects to. Why native: on a CPU the torch code writes every looked-up
 * channel to memory and reads it back for the dot product, and ATen's grid_sample gathers each
 * channel of each corner separately. Here the descriptors are channels-last (one 8-float block
 * a pixel), so a corner is one eight-float load, and nothing but the cost is written: about 3x
 * faster than the torch code on one x86-64 core.
 *
 * Same numbers: ATen's vectorised CPU kernels contract their multiply-adds into FMAs (addcmul,
 * grid_sample's corner sum), so those operations are written here as FMAs in the same order,
 * and the rest without contraction (built with -ffp-contract=off); sums run in torch's order.
 * On the machines this was checked on every cost is bit-identical to the torch code's
 * (test/test_native_matching_cost.py).
 *
 * Layout: a descriptor table (H * W + 1, 8) floats, channels-last, the descriptor channels
 * 0..C-1 and the visibility in channel C, its last block zeros (what an out-of-image corner
 * reads); key (C, .) channel rows with stride ks.
 */
#include <math.h>
#include <stdint.h>

#include "filter_native.h"
#include "simd8.h"

#define LANES 8

/* The looked-up descriptor block (8 channels) of one point a + p b, as grid_sample computes it;
 * `a`, `b` are the normalised projection's three coordinates (a + rho b: torch's addcmul). */
static void lookup_one(const float *F, int H, int W, float a0, float a1, float a2, float b0, float b1,
                       float b2, float p, float v[LANES]) {
    float sx = (float)(W - 1) / 2, sy = (float)(H - 1) / 2;
    float w = fmaf(p, b2, a2);
    w = (1e-4f > w) ? 1e-4f : w; /* clamp(min=1e-4); a NaN stays NaN */
    float gx = fmaf(p, b0, a0) / w, gy = fmaf(p, b1, a1) / w;
    float ix = (gx + 1.0f) * sx, iy = (gy + 1.0f) * sy;
    float x_w = floorf(ix), y_n = floorf(iy);
    float wx = ix - x_w, e = 1.0f - wx, n = iy - y_n, s = 1.0f - n;
    float nw = s * e, ne = s * wx, sw = n * e, se = n * wx;
    int wm = (x_w > -1.0f) && (x_w < (float)W), em = (x_w + 1.0f > -1.0f) && (x_w + 1.0f < (float)W);
    int nm = (y_n > -1.0f) && (y_n < (float)H), sm = (y_n + 1.0f > -1.0f) && (y_n + 1.0f < (float)H);
    int64_t zero = (int64_t)H * W;
    int64_t xi = (wm || em) ? (int64_t)x_w : 0, yi = (nm || sm) ? (int64_t)y_n : 0;
    const float *pnw = F + LANES * ((nm && wm) ? yi * W + xi : zero);
    const float *pne = F + LANES * ((nm && em) ? yi * W + xi + 1 : zero);
    const float *psw = F + LANES * ((sm && wm) ? (yi + 1) * W + xi : zero);
    const float *pse = F + LANES * ((sm && em) ? (yi + 1) * W + xi + 1 : zero);
    for (int c = 0; c < LANES; c++) v[c] = fmaf(pse[c], se, fmaf(psw[c], sw, fmaf(pne[c], ne, pnw[c] * nw)));
}

static inline v8f in_range(v8f x, v8f size) {
    return v8_and_ps(v8_cmp_ps(x, v8_set1_ps(-1.0f), V8_CMP_GT), v8_cmp_ps(x, size, V8_CMP_LT));
}

/* The corner index of eight lookups, or the zero block where the corner is out of the image. */
static inline v8i corner(v8i at, v8f inside, v8i zero) {
    return v8_blendv_epi8(zero, at, v8_castps_si256(inside));
}

/* Eight lookups at once (lane j: the point a_j + p_j b_j): v[j] is lookup j's descriptor block. */
static inline void lookup_eight(const float *F, int H, int W, v8f a0, v8f a1, v8f a2, v8f b0,
                                v8f b1, v8f b2, v8f p, v8f v[8]) {
    const v8f one = v8_set1_ps(1.0f), lo = v8_set1_ps(1e-4f);
    const v8f fw = v8_set1_ps((float)W), fh = v8_set1_ps((float)H);
    const v8f sx = v8_set1_ps((float)(W - 1) / 2), sy = v8_set1_ps((float)(H - 1) / 2);
    const v8i iw = v8_set1_epi32(W), izero = v8_set1_epi32(H * W), ione = v8_set1_epi32(1);
    /* a + rho b (addcmul), w clamped below at 1e-4 (max(lo, w) keeps a NaN w) */
    v8f w = v8_max_ps(lo, v8_fmadd_ps(p, b2, a2));
    v8f gx = v8_div_ps(v8_fmadd_ps(p, b0, a0), w);
    v8f gy = v8_div_ps(v8_fmadd_ps(p, b1, a1), w);
    /* grid_sample: unnormalised (align_corners), the four corners and their weights */
    v8f ix = v8_mul_ps(v8_add_ps(gx, one), sx), iy = v8_mul_ps(v8_add_ps(gy, one), sy);
    v8f xw = v8_floor_ps(ix), yn = v8_floor_ps(iy);
    v8f wx = v8_sub_ps(ix, xw), e = v8_sub_ps(one, wx);
    v8f n = v8_sub_ps(iy, yn), sv = v8_sub_ps(one, n);
    float wt[4][8];
    v8_storeu_ps(wt[0], v8_mul_ps(sv, e));
    v8_storeu_ps(wt[1], v8_mul_ps(sv, wx));
    v8_storeu_ps(wt[2], v8_mul_ps(n, e));
    v8_storeu_ps(wt[3], v8_mul_ps(n, wx));
    v8f wm = in_range(xw, fw), em = in_range(v8_add_ps(xw, one), fw);
    v8f nm = in_range(yn, fh), sm = in_range(v8_add_ps(yn, one), fh);
    /* lanes with no corner inside are not converted (their coordinate may be NaN or huge) */
    v8i xi = v8_cvttps_epi32(v8_and_ps(xw, v8_or_ps(wm, em)));
    v8i yi = v8_cvttps_epi32(v8_and_ps(yn, v8_or_ps(nm, sm)));
    v8i at = v8_add_epi32(v8_mullo_epi32(yi, iw), xi);
    v8i below = v8_add_epi32(at, iw);
    int32_t idx[4][8];
    v8_storeu_si256((v8i *)idx[0], corner(at, v8_and_ps(nm, wm), izero));
    v8_storeu_si256((v8i *)idx[1], corner(v8_add_epi32(at, ione), v8_and_ps(nm, em), izero));
    v8_storeu_si256((v8i *)idx[2], corner(below, v8_and_ps(sm, wm), izero));
    v8_storeu_si256((v8i *)idx[3], corner(v8_add_epi32(below, ione), v8_and_ps(sm, em), izero));
    for (int j = 0; j < 8; j++) {
        v8f acc = v8_mul_ps(v8_loadu_ps(F + (int64_t)LANES * idx[0][j]), v8_set1_ps(wt[0][j]));
        acc = v8_fmadd_ps(v8_loadu_ps(F + (int64_t)LANES * idx[1][j]), v8_set1_ps(wt[1][j]), acc);
        acc = v8_fmadd_ps(v8_loadu_ps(F + (int64_t)LANES * idx[2][j]), v8_set1_ps(wt[2][j]), acc);
        v[j] = v8_fmadd_ps(v8_loadu_ps(F + (int64_t)LANES * idx[3][j]), v8_set1_ps(wt[3][j]), acc);
    }
}

/* Eight rows' values x[0..valid) in lanes, the spare lanes repeating the last row (a block at
 * the end of the rows: computed, never written back). */
static inline v8f load_lanes(const float *x, int valid) {
    if (valid == 8) return v8_loadu_ps(x);
    float t[8];
    for (int j = 0; j < 8; j++) t[j] = x[j < valid ? j : valid - 1];
    return v8_loadu_ps(t);
}

/* The first `valid` lanes of v to x[0..valid). */
static inline void store_lanes(float *x, v8f v, int valid) {
    if (valid == 8) {
        v8_storeu_ps(x, v);
        return;
    }
    float t[8];
    v8_storeu_ps(t, v);
    for (int j = 0; j < valid; j++) x[j] = t[j];
}

/* filter_search._frame_cost_torch for eight rows (lanes) at inverse depths p: the ZNCC
 * (planes[0] keys[0], then addcmul_ per channel) and (count - zncc + 1e-3) / ((count + 1e-3)
 * * (count >= 0.5)). */
static inline v8f cost_eight(const float *F, int H, int W, int C, const v8f *k, v8f a0, v8f a1,
                                v8f a2, v8f B0, v8f B1, v8f B2, v8f p) {
    const v8f one = v8_set1_ps(1.0f), eps = v8_set1_ps(1e-3f), half = v8_set1_ps(0.5f);
    v8f v[8];
    lookup_eight(F, H, W, a0, a1, a2, B0, B1, B2, p, v);
    transpose8(v); /* v[c]: channel c of the eight lookups */
    v8f z = v8_mul_ps(v[0], k[0]);
    for (int c = 1; c < C; c++) z = v8_fmadd_ps(v[c], k[c], z);
    v8f count = v[C];
    v8f vis = v8_and_ps(v8_cmp_ps(count, half, V8_CMP_GE), one);
    v8f num = v8_add_ps(v8_sub_ps(count, z), eps);
    return v8_div_ps(num, v8_mul_ps(v8_add_ps(count, eps), vis));
}

/* The rays and key descriptors of the eight rows from r (the last block padded: load_lanes). */
static inline void rows_eight(const float *key, int64_t ks, int C, const float *a, int64_t as, int64_t r, int valid,
                              v8f *k, v8f *a0, v8f *a1, v8f *a2) {
    *a0 = load_lanes(a + r, valid), *a1 = load_lanes(a + as + r, valid), *a2 = load_lanes(a + 2 * as + r, valid);
    for (int c = 0; c < C; c++) k[c] = load_lanes(key + c * ks + r, valid);
}

/* One frame, samples-first: a (3, .) the rows' normalised projections at infinity with stride
 * as, b the frame's normalised K t, rho and out (S, .) with row stride rs; R rows, in blocks of
 * eight over `threads` OpenMP threads (torch's own libgomp: the same thread team). */
void frame_cost(const float *F, int H, int W, int C, const float *key, int64_t ks, const float *a, int64_t as,
                float b0, float b1, float b2, const float *rho, int64_t rs, int S, int64_t R, float *out,
                int threads) {
    const v8f B0 = v8_set1_ps(b0), B1 = v8_set1_ps(b1), B2 = v8_set1_ps(b2);
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t r = 0; r < R; r += 8) {
        int valid = (R - r < 8) ? (int)(R - r) : 8;
        v8f k[LANES], a0, a1, a2;
        rows_eight(key, ks, C, a, as, r, valid, k, &a0, &a1, &a2);
        for (int s = 0; s < S; s++) {
            v8f p = load_lanes(rho + s * rs + r, valid);
            store_lanes(out + s * rs + r, cost_eight(F, H, W, C, k, a0, a1, a2, B0, B1, B2, p), valid);
        }
    }
}

/* cost_volume.sample_cost_torch: the ZNCC of the summed lookups (mul_, then a sum over the
 * channels in order) and (count - zncc + 1e-3) / (count + 1e-3). */
static inline float sweep_one(const float *v, const float *key, int64_t ks, int C, int64_t m) {
    float z = v[0] * key[m];
    for (int c = 1; c < C; c++) z = z + v[c] * key[c * ks + m];
    return ((v[C] - z) + 1e-3f) / (v[C] + 1e-3f);
}

/* n neighbours, rows-first: F n tables of (H * W + 1) blocks one after the other; a (n, M, 3)
 * contiguous, the rows' normalised projections at infinity in each neighbour; b (n, 3); rho
 * (M, S) with row stride rs (0: the same S inverse depths for every row); cost and count
 * (M, S) contiguous; M rows over `threads` OpenMP threads. */
void sweep_cost(const float *F, int n, int H, int W, int C, const float *key, int64_t ks, const float *a,
                int64_t M, const float *b, const float *rho, int64_t rs, int S, float *cost, float *count,
                int threads) {
    const int64_t table = ((int64_t)H * W + 1) * LANES;
    const int s8 = S & ~7;
    const v8f eps = v8_set1_ps(1e-3f);
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t m = 0; m < M; m++) {
        const float *pm = rho + m * rs;
        for (int s = 0; s < s8; s += 8) {
            v8f p = v8_loadu_ps(pm + s), sum[8], v[8];
            for (int k = 0; k < n; k++) {
                const float *ak = a + (k * M + m) * 3, *bk = b + 3 * k;
                lookup_eight(F + k * table, H, W, v8_set1_ps(ak[0]), v8_set1_ps(ak[1]), v8_set1_ps(ak[2]),
                             v8_set1_ps(bk[0]), v8_set1_ps(bk[1]), v8_set1_ps(bk[2]), p, k ? v : sum);
                if (k)
                    for (int j = 0; j < 8; j++) sum[j] = v8_add_ps(sum[j], v[j]);
            }
            transpose8(sum); /* sum[c]: channel c of the eight samples, summed over the neighbours */
            v8f z = v8_mul_ps(sum[0], v8_set1_ps(key[m]));
            for (int c = 1; c < C; c++) z = v8_add_ps(z, v8_mul_ps(sum[c], v8_set1_ps(key[c * ks + m])));
            v8f num = v8_add_ps(v8_sub_ps(sum[C], z), eps);
            v8_storeu_ps(cost + m * S + s, v8_div_ps(num, v8_add_ps(sum[C], eps)));
            v8_storeu_ps(count + m * S + s, sum[C]);
        }
        for (int s = s8; s < S; s++) {
            float total[LANES], v[LANES];
            for (int k = 0; k < n; k++) {
                const float *ak = a + (k * M + m) * 3, *bk = b + 3 * k;
                lookup_one(F + k * table, H, W, ak[0], ak[1], ak[2], bk[0], bk[1], bk[2], pm[s], k ? v : total);
                if (k)
                    for (int c = 0; c < LANES; c++) total[c] = total[c] + v[c];
            }
            cost[m * S + s] = sweep_one(total, key, ks, C, m);
            count[m * S + s] = total[C];
        }
    }
}

/* ---- The filter's search of one bucket (filter_search._search_rows), whole, per row ---- */

/* _min0 (and min(dim=0) where a cost is NaN): the lowest of n costs at stride 8 and its first index. */
static inline int first_min(const float *c, int n, float *value) {
    int best = 0;
    for (int s = 0; s < n; s++) {
        if (isnan(c[8 * s])) { *value = c[8 * s]; return s; }
        if (c[8 * s] < c[8 * best]) best = s;
    }
    *value = c[8 * best];
    return best;
}

/* _distinctiveness: 1 - c1 / c2 over the local minima more than one sample from the best. */
static float distinctiveness(const float *c, int S, int best, float c1) {
    float c2 = INFINITY;
    int nan = 0;
    for (int s = 0; s < S; s++) {
        float x = c[8 * s];
        if (isnan(x)) { nan = 1; continue; }
        int is_min = (s == S - 1 || x <= c[8 * (s + 1)]) && (s == 0 || x <= c[8 * (s - 1)]);
        if (is_min && (s < best - 1 || s > best + 1) && x < c2) c2 = x;
    }
    /* cost / is_min: a NaN anywhere outside the best's neighbours makes amin NaN */
    if (nan) {
        for (int s = 0; s < S; s++)
            if (isnan(c[8 * s]) && (s < best - 1 || s > best + 1)) c2 = NAN;
    }
    if (!isfinite(c2)) { /* a single basin: the largest finite cost (nan_to_num: NaN 0, inf -1) */
        float largest = -INFINITY;
        for (int s = 0; s < S; s++) {
            float x = c[8 * s];
            x = isnan(x) ? 0.0f : (x == INFINITY ? -1.0f : (x == -INFINITY ? -3.4028234663852886e38f : x));
            if (x > largest) largest = x;
        }
        c2 = largest;
    }
    float d = 1.0f - c1 / (c2 < 1e-6f ? 1e-6f : c2);
    return (d < 0.0f) ? 0.0f : ((d > 1.0f) ? 1.0f : d);
}

/* _parabola through samples j-1, j, j+1 (costs at stride 8); g the sample j's inverse depth. */
static inline void parabola(float cm, float c0, float cp, float c1, float g, float step, float *rho, float *cost,
                            uint8_t *ok) {
    float curvature = (cm - 2.0f * c0) + cp;
    int good = (curvature > 0.0f) && (curvature < INFINITY) && isfinite(c1);
    float half_slope = (cm - cp) * 0.5f;
    float delta = half_slope / (good ? curvature : 1.0f);
    delta = (delta < -1.0f) ? -1.0f : ((delta > 1.0f) ? 1.0f : delta);
    *rho = g + delta * step;
    *cost = good ? c0 - 0.5f * (half_slope * delta) : INFINITY;
    *ok = (uint8_t)good;
}

/* One block of eight rows (lanes; only the first `valid` written): S coarse samples in
 * [lo, hi], the best, its distinctiveness, `refine` fine samples each side and the parabola. */
static void search_eight(const float *F, int H, int W, int C, const v8f *k, v8f a0, v8f a1, v8f a2,
                         v8f B0, v8f B1, v8f B2, v8f lo, v8f hi, int S, int refine, int with_distinct,
                         int reject_edges, int valid, float *rho, float *cost, float *distinct, uint8_t *ok,
                         float *costs /* (S + 2 refine) x 8 */) {
    v8f step = v8_div_ps(v8_sub_ps(hi, lo), v8_set1_ps((float)(S - 1)));
    for (int s = 0; s < S; s++) {
        v8f p = v8_fmadd_ps(step, v8_set1_ps((float)s), lo); /* addcmul(lo, step, k) */
        v8_storeu_ps(costs + 8 * s, cost_eight(F, H, W, C, k, a0, a1, a2, B0, B1, B2, p));
    }
    float los[8], steps[8], gbest[8], fsteps[8], c1s[8];
    int bests[8];
    v8_storeu_ps(los, lo);
    v8_storeu_ps(steps, step);
    for (int j = 0; j < 8; j++) {
        bests[j] = first_min(costs + j, S, &c1s[j]);
        gbest[j] = fmaf(steps[j], (float)bests[j], los[j]);
        fsteps[j] = steps[j] / (float)(refine > 0 ? refine : 1);
    }
    float *fine = costs + 8 * S; /* the 2 refine fine costs, the best coarse one's left out */
    if (refine > 0) {
        v8f gb = v8_loadu_ps(gbest), fs = v8_loadu_ps(fsteps);
        for (int o = -refine, i = 0; o <= refine; o++) {
            if (o == 0) continue;
            v8f p = v8_fmadd_ps(fs, v8_set1_ps((float)o), gb);
            v8_storeu_ps(fine + 8 * i++, cost_eight(F, H, W, C, k, a0, a1, a2, B0, B1, B2, p));
        }
    }
    for (int j = 0; j < valid; j++) {
        const float *c = costs + j;
        int best = bests[j];
        float c1 = c1s[j];
        distinct[j] = with_distinct ? distinctiveness(c, S, best, c1) : c1;
        if (refine == 0) {
            int m = best < 1 ? 1 : (best > S - 2 ? S - 2 : best);
            parabola(c[8 * (m - 1)], c[8 * m], c[8 * (m + 1)], c1, fmaf(steps[j], (float)m, los[j]), steps[j],
                     &rho[j], &cost[j], &ok[j]);
        } else {
            float f[(2 * 64 + 1) * 8]; /* the fine costs in order at stride 8, the middle one c1 */
            float fv;
            for (int i = 0; i < refine; i++) f[i * 8] = fine[8 * i + j];
            f[refine * 8] = c1;
            for (int i = 0; i < refine; i++) f[(refine + 1 + i) * 8] = fine[8 * (refine + i) + j];
            int m = first_min(f, 2 * refine + 1, &fv);
            m = m < 1 ? 1 : (m > 2 * refine - 1 ? 2 * refine - 1 : m);
            float g = fmaf(fsteps[j], (float)(m - refine), gbest[j]);
            parabola(f[8 * (m - 1)], f[8 * m], f[8 * (m + 1)], c1, g, fsteps[j], &rho[j], &cost[j], &ok[j]);
        }
        if (reject_edges && (best <= 0 || best >= S - 1)) ok[j] = 0;
    }
}

/* filter_search._search_rows of R rows (one bucket): key (C, .) stride ks, a (3, .) stride as,
 * lo and hi (R,); out rho, cost, distinct (R,) and ok (R,) bytes; blocks of eight rows over
 * `threads` OpenMP threads. S at most 512, refine at most 64 (the caller checks). */
void frame_search(const float *F, int H, int W, int C, const float *key, int64_t ks, const float *a, int64_t as,
                  float b0, float b1, float b2, const float *lo, const float *hi, int64_t R, int S, int refine,
                  int with_distinct, int reject_edges, float *rho, float *cost, float *distinct, uint8_t *ok,
                  int threads) {
    const v8f B0 = v8_set1_ps(b0), B1 = v8_set1_ps(b1), B2 = v8_set1_ps(b2);
    const int64_t blocks = (R + 7) / 8;
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t i = 0; i < blocks; i++) {
        float costs[(512 + 2 * 64) * 8];
        int64_t r = 8 * i;
        int valid = (R - r < 8) ? (int)(R - r) : 8;
        v8f k[LANES], a0, a1, a2;
        rows_eight(key, ks, C, a, as, r, valid, k, &a0, &a1, &a2);
        v8f l = load_lanes(lo + r, valid), h = load_lanes(hi + r, valid);
        search_eight(F, H, W, C, k, a0, a1, a2, B0, B1, B2, l, h, S, refine, with_distinct, reject_edges, valid,
                     rho + r, cost + r, distinct + r, ok + r, costs);
    }
}

/* ---- The filter's rows of one frame: helpers, the first-measurement check, then filter_rows ---- */


/* The first-measurement check (filter_first_check.check_first_matches) of the n first measurements
 * first[0..n) (positions in the searched rows): each searched again over x +- px / jx in S samples
 * (refine 0, the second-best ratio), distinct where that search is ok, its ratio at least dmin and
 * its match in [rho_min, rho_max]; there the window's best replaces the match and its cost. The
 * motion is taken at the match, and valid says distinct. a (3, .) stride as: the searched rows'
 * projections at infinity in pixels (b: K t), s0 s1 grid_sample's scale. */
static void check_first(const float *F, int H, int W, int C, const float *key, int64_t ks, const int64_t *rows,
                        const float *a, int64_t as, float b0, float b1, float b2, float s0, float s1, float *x,
                        float *jx, float *cost, uint8_t *valid, const int64_t *first, int64_t n, float px, int S,
                        float dmin, float rho_min, float rho_max, int threads) {
    /* filter_geometry.grid_rows_in_place: (b_k s_k) - b_2 for the two image coordinates */
    const float nb0 = b0 * s0 - b2, nb1 = b1 * s1 - b2;
    const v8f B0 = v8_set1_ps(nb0), B1 = v8_set1_ps(nb1), B2 = v8_set1_ps(b2);
    const int64_t blocks = (n + 7) / 8;
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t blk = 0; blk < blocks; blk++) {
        float costs[(512 + 2 * 64) * 8];
        int valid_lanes = (n - 8 * blk < 8) ? (int)(n - 8 * blk) : 8;
        float kl[LANES][8], l0[8], l1[8], l2[8], lo[8], hi[8], match[8];
        for (int j = 0; j < 8; j++) {
            int64_t i = first[8 * blk + (j < valid_lanes ? j : valid_lanes - 1)], r = rows[i];
            for (int c = 0; c < C; c++) kl[c][j] = key[c * ks + r];
            float a2 = a[2 * as + i];
            l0[j] = a[i] * s0 - a2; /* a[:2].mul_(scale).sub_(a[2]) */
            l1[j] = a[as + i] * s1 - a2;
            l2[j] = a2;
            float half = (1.0f / clamp_below(jx[i], 1e-6f)) * px; /* px / clamp(jx): reciprocal(t) * p */
            match[j] = x[i];
            lo[j] = match[j] - half;
            hi[j] = match[j] + half;
        }
        v8f k[LANES];
        for (int c = 0; c < C; c++) k[c] = v8_loadu_ps(kl[c]);
        float rho[8], best[8], ratio[8];
        uint8_t ok[8];
        search_eight(F, H, W, C, k, v8_loadu_ps(l0), v8_loadu_ps(l1), v8_loadu_ps(l2), B0, B1, B2,
                     v8_loadu_ps(lo), v8_loadu_ps(hi), S, 0, 1, 0, valid_lanes, rho, best, ratio, ok, costs);
        for (int j = 0; j < valid_lanes; j++) {
            int64_t i = first[8 * blk + j];
            int distinct = ok[j] && ratio[j] >= dmin && rho[j] >= rho_min && rho[j] <= rho_max;
            if (distinct) {
                x[i] = rho[j];
                cost[i] = best[j];
            }
            jx[i] = row_motion_one(a[i], a[as + i], a[2 * as + i], b0, b1, b2, x[i]);
            valid[i] = (uint8_t)distinct;
        }
    }
}

/* ---- A frame's searches of the filter's chosen rows, whole (filter_frame_update: search_rows, the
 * validity tests, the first-measurement check) ---- */

/* torch.maximum: NaN if either is NaN */
static inline float max_nan(float u, float v) { return (u != u || v != v) ? NAN : (u > v ? u : v); }

/* The R rows of one frame: spans, buckets, searches, tests and first-measurement check.
 * rows (R,) the keyframe rows chosen, updates (M,) their measurement counts, fresh (R,) bytes: no
 * prior (a whole-range or bracketed search), bracketed (R,) bytes or NULL; a (3, .) stride as the
 * rows' projections at infinity in pixels, b K t, s0 s1 grid_sample's scale; j (R,) the epipolar
 * motion at the prior, lo hi (R,) the intervals. The buckets (filter_buckets): samples, refine and
 * the distinctiveness switch of verify, short, medium and long in bucket[0..12), the span limits of
 * short, verify and medium in limit[0..3) (verify and medium off where their samples are 0); tests
 * max_cost, min_distinct, reject_edges; the range; the check's px, samples and ratio (px 0: off).
 * Out: x, jx, cost (R,) and valid (R,) bytes; scratch (2 R,) int64. */
void filter_rows(const float *F, int H, int W, int C, const float *key, int64_t ks, const int64_t *rows,
                 const int64_t *updates, const uint8_t *fresh, const uint8_t *bracketed, const float *a, int64_t as,
                 float b0, float b1, float b2, float s0, float s1, const float *j, const float *lo, const float *hi,
                 int64_t R, const int *bucket, const float *limit, float max_cost, float min_distinct,
                 int reject_edges, float rho_min, float rho_max, float check_px, int check_samples, float check_dmin,
                 float *x, float *jx, float *cost, uint8_t *valid, int64_t *scratch, int threads,
                 int64_t min_lookups) {
    int64_t *order = scratch, *first = scratch + R;
    int64_t counts[4] = {0, 0, 0, 0};
    uint8_t *which = (uint8_t *)first; /* each row's bucket, before `first` is needed */
    const int use_verify = bucket[0] > 0, use_medium = bucket[6] > 0;
    for (int64_t i = 0; i < R; i++) {
        /* search_rows: the interval in px (a whole-range search: the larger motion of its ends) */
        float span = j[i] * (hi[i] - lo[i]);
        if (fresh[i]) {
            float a0 = a[i], a1 = a[as + i], a2 = a[2 * as + i];
            float ends = max_nan(row_motion_one(a0, a1, a2, b0, b1, b2, lo[i]),
                                 row_motion_one(a0, a1, a2, b0, b1, b2, hi[i]));
            span = ends * (hi[i] - lo[i]);
        }
        /* filter_buckets.bucket_members: the first bucket whose test the row passes */
        int known = !fresh[i];
        int is_short = known && span <= limit[0];
        int is_verify = use_verify && known && span <= limit[1];
        is_short = is_short && !is_verify;
        int rest = !is_short && !is_verify;
        int is_medium = use_medium && span <= limit[2] && rest;
        uint8_t b = is_verify ? 0 : (is_short ? 1 : (is_medium ? 2 : 3));
        which[i] = b;
        counts[b]++;
    }
    int64_t start[4], fill[4];
    start[0] = 0;
    for (int b = 1; b < 4; b++) start[b] = start[b - 1] + counts[b - 1];
    for (int b = 0; b < 4; b++) fill[b] = start[b];
    for (int64_t i = 0; i < R; i++) order[fill[which[i]]++] = i; /* a counting sort: row order within a bucket */
    const float nb0 = b0 * s0 - b2, nb1 = b1 * s1 - b2;
    const v8f B0 = v8_set1_ps(nb0), B1 = v8_set1_ps(nb1), B2 = v8_set1_ps(b2);
    for (int bk = 0; bk < 4; bk++) {
        const int64_t n = counts[bk];
        const int S = bucket[3 * bk], refine = bucket[3 * bk + 1], distinct = bucket[3 * bk + 2];
        if (n == 0) continue;
        const int64_t *members = order + start[bk];
        const int team = (n * (S + 2 * refine) >= min_lookups) ? threads : 1;
        const int64_t blocks = (n + 7) / 8;
#pragma omp parallel for num_threads(team) schedule(static) if (team > 1)
        for (int64_t blk = 0; blk < blocks; blk++) {
            float costs[(512 + 2 * 64) * 8];
            int lanes = (n - 8 * blk < 8) ? (int)(n - 8 * blk) : 8;
            float kl[LANES][8], l0[8], l1[8], l2[8], l[8], h[8];
            for (int q = 0; q < 8; q++) {
                int64_t i = members[8 * blk + (q < lanes ? q : lanes - 1)], r = rows[i];
                for (int c = 0; c < C; c++) kl[c][q] = key[c * ks + r];
                float a2 = a[2 * as + i];
                l0[q] = a[i] * s0 - a2; /* grid_rows_in_place */
                l1[q] = a[as + i] * s1 - a2;
                l2[q] = a2;
                l[q] = lo[i];
                h[q] = hi[i];
            }
            v8f k[LANES];
            for (int c = 0; c < C; c++) k[c] = v8_loadu_ps(kl[c]);
            float rho[8], best[8], ratio[8];
            uint8_t ok[8];
            search_eight(F, H, W, C, k, v8_loadu_ps(l0), v8_loadu_ps(l1), v8_loadu_ps(l2), B0, B1, B2,
                         v8_loadu_ps(l), v8_loadu_ps(h), S, refine, distinct, reject_edges, lanes, rho, best,
                         ratio, ok, costs);
            for (int q = 0; q < lanes; q++) {
                int64_t i = members[8 * blk + q];
                int good = ok[q] && best[q] <= max_cost;
                if (distinct) good = good && ratio[q] >= min_distinct;
                x[i] = rho[q];
                cost[i] = best[q];
                valid[i] = (uint8_t)good;
            }
        }
    }
    /* _update_rows: the motion at the match, a bracket's edge test, the range and the motion test */
    for (int64_t i = 0; i < R; i++) {
        float m = row_motion_one(a[i], a[as + i], a[2 * as + i], b0, b1, b2, x[i]);
        int good = valid[i];
        if (bracketed && bracketed[i]) good = good && ((x[i] - lo[i]) * m >= 0.5f) && ((hi[i] - x[i]) * m >= 0.5f);
        good = good && x[i] >= rho_min && x[i] <= rho_max && m > 1e-6f;
        jx[i] = m;
        valid[i] = (uint8_t)good;
    }
    if (check_px <= 0.0f) return;
    int64_t n = 0;
    for (int64_t i = 0; i < R; i++)
        if (valid[i] && updates[rows[i]] == 0) first[n++] = i;
    int team = (n * check_samples >= min_lookups) ? threads : 1;
    check_first(F, H, W, C, key, ks, rows, a, as, b0, b1, b2, s0, s1, x, jx, cost, valid, first, n, check_px,
                check_samples, check_dmin, rho_min, rho_max, team);
}

/* The descriptors' channels-last table (native_cost._channels_last): n images of `ch` channels
 * of HW pixels, element (k, c, p) at desc[k sn + c sc + p sp], into n tables of HW + 1 blocks of
 * eight floats, the channels then zeros, and a zero block last (a copy: exact). Planar images
 * (sp 1) eight pixels at a time, their planes loaded and transposed; others (the filter's
 * frame descriptors are interleaved, sc 1) pixel by pixel. */
void channels_last(const float *desc, int n, int ch, int64_t HW, int64_t sn, int64_t sc, int64_t sp, float *table,
                   int threads) {
    const int64_t blocks = (sp == 1) ? HW / 8 : 0;
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t i = 0; i < n * blocks; i++) {
        int64_t k = i / blocks, p = (i % blocks) * 8;
        const float *d = desc + k * sn;
        float *t = table + (k * (HW + 1) + p) * LANES;
        v8f r[8];
        for (int c = 0; c < 8; c++) r[c] = (c < ch) ? v8_loadu_ps(d + c * sc + p) : v8_setzero_ps();
        transpose8(r);
        for (int j = 0; j < 8; j++) v8_storeu_ps(t + LANES * j, r[j]);
    }
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int k = 0; k < n; k++) {
        const float *d = desc + k * sn;
        float *t = table + k * (HW + 1) * LANES;
        for (int64_t p = blocks * 8; p <= HW; p++) /* the pixels left (all, if not planar), then the zero block */
            for (int c = 0; c < LANES; c++) t[p * LANES + c] = (p < HW && c < ch) ? d[c * sc + p * sp] : 0.0f;
    }
}
