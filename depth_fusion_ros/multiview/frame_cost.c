/* The depth filter's epipolar matching cost against one frame, in one pass (x86-64, AVX2 + FMA).
 *
 * What it computes is filter_search._frame_cost's torch code, number for number: for every
 * keyframe row r and sample s, the frame's descriptors looked up bilinearly where the row's
 * epipolar ray projects at inverse depth rho[s, r] (grid_sample, zero padding, align_corners),
 * their ZNCC with the row's key descriptor, and 1 - ZNCC normalised by the looked-up visibility
 * (inf where the frame does not see the sample). Why it exists: on a CPU the torch code writes
 * every looked-up channel to memory and reads it back for the dot product, and ATen's
 * grid_sample gathers each channel of each corner separately. Here the frame's descriptors are
 * channels-last (one 8-float block a pixel), so a corner is one 256-bit load, and nothing but
 * the cost is written: about 3x faster than the torch code on one core.
 *
 * Same numbers: ATen's vectorised CPU kernels contract their multiply-adds into FMAs (addcmul,
 * grid_sample's corner sum), so the same operations are written here as FMAs in the same
 * order, and the rest without contraction (built with -ffp-contract=off). On the machines this
 * was checked on every cost is bit-identical to the torch code's (test_native_frame_cost.py).
 *
 * Layout: F (H * W + 1, 8) floats, channels-last, the descriptor channels 0..C-1 and the
 * visibility in channel C, the last block zeros (what an out-of-image corner reads); key (C, .)
 * channel rows with stride ks; a (3, .) the rows' normalised projections at infinity with
 * stride as; b the frame's normalised K t; rho and out (S, .) with row stride rs. R rows.
 */
#include <immintrin.h>
#include <math.h>
#include <stdint.h>

#define LANES 8

/* One lookup and its cost: the tail rows of a block of eight (the same arithmetic, scalar). */
static void cost_one(const float *F, int H, int W, int C, const float *key, int64_t ks, const float *a,
                     int64_t as, float b0, float b1, float b2, float p, int64_t r, float *o) {
    float sx = (float)(W - 1) / 2, sy = (float)(H - 1) / 2;
    float w = fmaf(p, b2, a[2 * as + r]);
    w = (1e-4f > w) ? 1e-4f : w; /* clamp(min=1e-4); a NaN stays NaN */
    float gx = fmaf(p, b0, a[r]) / w, gy = fmaf(p, b1, a[as + r]) / w;
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
    float v[LANES];
    for (int c = 0; c < LANES; c++) v[c] = fmaf(pse[c], se, fmaf(psw[c], sw, fmaf(pne[c], ne, pnw[c] * nw)));
    float z = v[0] * key[r];
    for (int c = 1; c < C; c++) z = fmaf(v[c], key[c * ks + r], z);
    float count = v[C];
    float vis = (count >= 0.5f) ? 1.0f : 0.0f;
    *o = ((count - z) + 1e-3f) / ((count + 1e-3f) * vis);
}

static inline void transpose8(__m256 *r) {
    __m256 t0 = _mm256_unpacklo_ps(r[0], r[1]), t1 = _mm256_unpackhi_ps(r[0], r[1]);
    __m256 t2 = _mm256_unpacklo_ps(r[2], r[3]), t3 = _mm256_unpackhi_ps(r[2], r[3]);
    __m256 t4 = _mm256_unpacklo_ps(r[4], r[5]), t5 = _mm256_unpackhi_ps(r[4], r[5]);
    __m256 t6 = _mm256_unpacklo_ps(r[6], r[7]), t7 = _mm256_unpackhi_ps(r[6], r[7]);
    __m256 u0 = _mm256_shuffle_ps(t0, t2, 0x44), u1 = _mm256_shuffle_ps(t0, t2, 0xEE);
    __m256 u2 = _mm256_shuffle_ps(t1, t3, 0x44), u3 = _mm256_shuffle_ps(t1, t3, 0xEE);
    __m256 u4 = _mm256_shuffle_ps(t4, t6, 0x44), u5 = _mm256_shuffle_ps(t4, t6, 0xEE);
    __m256 u6 = _mm256_shuffle_ps(t5, t7, 0x44), u7 = _mm256_shuffle_ps(t5, t7, 0xEE);
    r[0] = _mm256_permute2f128_ps(u0, u4, 0x20);
    r[1] = _mm256_permute2f128_ps(u1, u5, 0x20);
    r[2] = _mm256_permute2f128_ps(u2, u6, 0x20);
    r[3] = _mm256_permute2f128_ps(u3, u7, 0x20);
    r[4] = _mm256_permute2f128_ps(u0, u4, 0x31);
    r[5] = _mm256_permute2f128_ps(u1, u5, 0x31);
    r[6] = _mm256_permute2f128_ps(u2, u6, 0x31);
    r[7] = _mm256_permute2f128_ps(u3, u7, 0x31);
}

static inline __m256 in_range(__m256 x, __m256 size) {
    return _mm256_and_ps(_mm256_cmp_ps(x, _mm256_set1_ps(-1.0f), _CMP_GT_OQ), _mm256_cmp_ps(x, size, _CMP_LT_OQ));
}

/* The corner index of eight lookups, or the zero block where the corner is out of the image. */
static inline __m256i corner(__m256i at, __m256 inside, __m256i zero) {
    return _mm256_blendv_epi8(zero, at, _mm256_castps_si256(inside));
}

void frame_cost(const float *F, int H, int W, int C, const float *key, int64_t ks, const float *a, int64_t as,
                float b0, float b1, float b2, const float *rho, int64_t rs, int S, int64_t R, float *out) {
    const __m256 one = _mm256_set1_ps(1.0f), lo = _mm256_set1_ps(1e-4f), eps = _mm256_set1_ps(1e-3f);
    const __m256 half = _mm256_set1_ps(0.5f), fw = _mm256_set1_ps((float)W), fh = _mm256_set1_ps((float)H);
    const __m256 sx = _mm256_set1_ps((float)(W - 1) / 2), sy = _mm256_set1_ps((float)(H - 1) / 2);
    const __m256 B0 = _mm256_set1_ps(b0), B1 = _mm256_set1_ps(b1), B2 = _mm256_set1_ps(b2);
    const __m256i iw = _mm256_set1_epi32(W), izero = _mm256_set1_epi32(H * W), ione = _mm256_set1_epi32(1);
    const int64_t r8 = R & ~(int64_t)7;
    for (int s = 0; s < S; s++) {
        const float *ps = rho + s * rs;
        float *os = out + s * rs;
        for (int64_t r = 0; r < r8; r += 8) {
            __m256 p = _mm256_loadu_ps(ps + r);
            /* filter_search._grid: a + rho b (addcmul), w clamped below at 1e-4 (a NaN stays) */
            __m256 w = _mm256_max_ps(lo, _mm256_fmadd_ps(p, B2, _mm256_loadu_ps(a + 2 * as + r)));
            __m256 gx = _mm256_div_ps(_mm256_fmadd_ps(p, B0, _mm256_loadu_ps(a + r)), w);
            __m256 gy = _mm256_div_ps(_mm256_fmadd_ps(p, B1, _mm256_loadu_ps(a + as + r)), w);
            /* grid_sample: unnormalised (align_corners), the four corners and their weights */
            __m256 ix = _mm256_mul_ps(_mm256_add_ps(gx, one), sx), iy = _mm256_mul_ps(_mm256_add_ps(gy, one), sy);
            __m256 xw = _mm256_floor_ps(ix), yn = _mm256_floor_ps(iy);
            __m256 wx = _mm256_sub_ps(ix, xw), e = _mm256_sub_ps(one, wx);
            __m256 n = _mm256_sub_ps(iy, yn), sv = _mm256_sub_ps(one, n);
            float wt[4][8];
            _mm256_storeu_ps(wt[0], _mm256_mul_ps(sv, e));
            _mm256_storeu_ps(wt[1], _mm256_mul_ps(sv, wx));
            _mm256_storeu_ps(wt[2], _mm256_mul_ps(n, e));
            _mm256_storeu_ps(wt[3], _mm256_mul_ps(n, wx));
            __m256 wm = in_range(xw, fw), em = in_range(_mm256_add_ps(xw, one), fw);
            __m256 nm = in_range(yn, fh), sm = in_range(_mm256_add_ps(yn, one), fh);
            /* lanes with no corner inside are not converted (their coordinate may be NaN or huge) */
            __m256i xi = _mm256_cvttps_epi32(_mm256_and_ps(xw, _mm256_or_ps(wm, em)));
            __m256i yi = _mm256_cvttps_epi32(_mm256_and_ps(yn, _mm256_or_ps(nm, sm)));
            __m256i at = _mm256_add_epi32(_mm256_mullo_epi32(yi, iw), xi);
            __m256i below = _mm256_add_epi32(at, iw);
            int32_t idx[4][8];
            _mm256_storeu_si256((__m256i *)idx[0], corner(at, _mm256_and_ps(nm, wm), izero));
            _mm256_storeu_si256((__m256i *)idx[1], corner(_mm256_add_epi32(at, ione), _mm256_and_ps(nm, em), izero));
            _mm256_storeu_si256((__m256i *)idx[2], corner(below, _mm256_and_ps(sm, wm), izero));
            _mm256_storeu_si256((__m256i *)idx[3], corner(_mm256_add_epi32(below, ione), _mm256_and_ps(sm, em), izero));
            __m256 v[8];
            for (int j = 0; j < 8; j++) {
                __m256 acc = _mm256_mul_ps(_mm256_loadu_ps(F + (int64_t)LANES * idx[0][j]), _mm256_set1_ps(wt[0][j]));
                acc = _mm256_fmadd_ps(_mm256_loadu_ps(F + (int64_t)LANES * idx[1][j]), _mm256_set1_ps(wt[1][j]), acc);
                acc = _mm256_fmadd_ps(_mm256_loadu_ps(F + (int64_t)LANES * idx[2][j]), _mm256_set1_ps(wt[2][j]), acc);
                v[j] = _mm256_fmadd_ps(_mm256_loadu_ps(F + (int64_t)LANES * idx[3][j]), _mm256_set1_ps(wt[3][j]), acc);
            }
            transpose8(v); /* v[c]: channel c of the eight lookups */
            __m256 z = _mm256_mul_ps(v[0], _mm256_loadu_ps(key + r));
            for (int c = 1; c < C; c++) z = _mm256_fmadd_ps(v[c], _mm256_loadu_ps(key + c * ks + r), z);
            __m256 count = v[C];
            __m256 vis = _mm256_and_ps(_mm256_cmp_ps(count, half, _CMP_GE_OQ), one);
            __m256 num = _mm256_add_ps(_mm256_sub_ps(count, z), eps);
            _mm256_storeu_ps(os + r, _mm256_div_ps(num, _mm256_mul_ps(_mm256_add_ps(count, eps), vis)));
        }
        for (int64_t r = r8; r < R; r++) cost_one(F, H, W, C, key, ks, a, as, b0, b1, b2, ps[r], r, os + r);
    }
}
