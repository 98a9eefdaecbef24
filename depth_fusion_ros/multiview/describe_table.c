/* A frame's matching descriptors written as the native kernels' table, in one pass on a CPU, in C
 * (descriptors.patch_descriptors, channels-last, one image).
 *
 * The filter describes every frame. With OpenCV that is a separable blur, one filter2D a channel
 * (six of the 3x3 patch's taps projected on its zero-mean basis), a plane of squared norms, its
 * square root and reciprocal, a product a channel and a merge into the table: a dozen walks over
 * the image and a dozen planes of fresh memory, about 1 ms at 320x240 on one thread. Here the
 * blur is two passes into one padded plane, then each row's taps are projected, normalised and
 * written interleaved straight into the table, eight pixels at a time (an 8x8 transpose). The
 * table is written through the cache, though in the filter's frame that costs as much again as
 * computing it (0.45 ms a frame in a loop, 0.95 in the frame): streamed past the cache it was
 * written in 0.65 ms, but the searches that read it next were 0.4-0.6 ms slower. The numbers are
 * OpenCV's (and torch's) to float32 rounding: the same sums in another order, and fused
 * multiply-adds (test/test_native_descriptors.py).
 *
 * image (h, w) grey, contiguous; blur (nb = 2 rb + 1) the blur's taps (border pixels repeated);
 * P taps at (dx[p], dy[p]) pixels from the centre (border pixels repeated), reach their largest
 * offset; basis (K, P) the projection; floor P eps^2 added to the squared norm; margin < 0: no
 * visibility band, else the descriptors are zeroed within margin px of the border and channel K is
 * 1 inside it, 0 in it. table ((h w + 1) lanes): pixel i's block at i lanes, the spare channels
 * zero, then one zero block. Rows split over threads: each is computed alone, the same numbers.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "simd8.h"

/* a pixel block (native_cost.LANES) and the most taps a patch has */
#define LANES 8
#define TAPS 9

static inline int64_t clamp_index(int64_t v, int64_t high) { return v < 0 ? 0 : (v > high ? high : v); }

/* the horizontal blur at one pixel of a row, its reads clamped to the row (border pixels repeated) */
static inline float blur_at(const float *src, int64_t w, int nb, const float *taps, int64_t x) {
    float s = 0.0f;
    for (int k = 0; k < nb; k++) s += taps[k] * src[clamp_index(x + k - nb / 2, w - 1)];
    return s;
}

/* one row of the horizontal blur: the ends pixel by pixel, the inside [lo, hi) as a sum of
 * shifted rows (vectorised) */
static void blur_row(const float *src, int64_t w, int nb, const float *taps, float *dst) {
    const int rb = nb / 2;
    const int64_t lo = rb < w ? rb : w, hi = (w - rb > lo) ? w - rb : lo;
    for (int64_t x = 0; x < lo; x++) dst[x] = blur_at(src, w, nb, taps, x);
    for (int64_t x = hi; x < w; x++) dst[x] = blur_at(src, w, nb, taps, x);
    for (int64_t x = lo; x < hi; x++) dst[x] = 0.0f;
    for (int k = 0; k < nb; k++) {
        const float t = taps[k];
        const float *shifted = src + k - rb;
        for (int64_t x = lo; x < hi; x++) dst[x] += t * shifted[x];
    }
}

/* one row of the vertical blur into the padded plane (reach repeated pixels on either side) */
static void blur_column(const float *rows, int64_t h, int64_t w, int64_t y, int nb, const float *taps, int reach,
                        float *dst) {
    const int rb = nb / 2;
    float *out = dst + reach;
    for (int64_t x = 0; x < w; x++) out[x] = 0.0f;
    for (int k = 0; k < nb; k++) {
        const float *src = rows + clamp_index(y + k - rb, h - 1) * w;
        const float t = taps[k];
        for (int64_t x = 0; x < w; x++) out[x] += t * src[x];
    }
    for (int i = 0; i < reach; i++) {
        dst[i] = out[0];
        out[w + i] = out[w - 1];
    }
    for (int i = reach; i < reach + 8; i++) out[w + i] = 0.0f;
}

/* one row of descriptors, eight pixels at a time: the taps (TAPS, unused ones weighted 0)
 * projected on the basis (LANES x TAPS, unused channels 0), the squared norm over the K channels,
 * the reciprocal of its root (0 in the band), then the block of each pixel written whole */
static void describe_row(const float *padded, int64_t h, int64_t w, int64_t wp, int64_t y, const int *dx,
                         const int *dy, int reach, int K, const float *basis, float floor_, int margin, float *out) {
    const float *src[TAPS];
    for (int p = 0; p < TAPS; p++) src[p] = padded + clamp_index(y + dy[p], h - 1) * wp + reach + dx[p];
    const int banded = margin >= 0;
    const int row_inside = !banded || (y >= margin && y < h - margin);
    const v8f lane = v8_setr_ps(0, 1, 2, 3, 4, 5, 6, 7);
    for (int64_t x0 = 0; x0 < w; x0 += 8) {
        v8f tap[TAPS], r[LANES];
        for (int p = 0; p < TAPS; p++) tap[p] = v8_loadu_ps(src[p] + x0);
        v8f total = v8_set1_ps(floor_);
        for (int c = 0; c < LANES; c++) {
            v8f acc = v8_mul_ps(v8_broadcast_ss(basis + c * TAPS), tap[0]);
            for (int p = 1; p < TAPS; p++) acc = v8_fmadd_ps(v8_broadcast_ss(basis + c * TAPS + p), tap[p], acc);
            r[c] = acc;
            if (c < K) total = v8_fmadd_ps(acc, acc, total);
        }
        v8f scale = v8_div_ps(v8_set1_ps(1.0f), v8_sqrt_ps(total));
        if (banded) {
            const v8f x = v8_add_ps(v8_set1_ps((float)x0), lane);
            const v8f in = v8_and_ps(v8_cmp_ps(x, v8_set1_ps((float)margin), V8_CMP_GE),
                                            v8_cmp_ps(x, v8_set1_ps((float)(w - margin)), V8_CMP_LT));
            const v8f inside = row_inside ? v8_and_ps(in, v8_set1_ps(1.0f)) : v8_setzero_ps();
            scale = v8_mul_ps(scale, inside);
            r[K] = inside;
        }
        for (int c = 0; c < K; c++) r[c] = v8_mul_ps(r[c], scale);
        transpose8(r);
        const int64_t n = (w - x0 < 8) ? w - x0 : 8;
        for (int64_t i = 0; i < n; i++) v8_storeu_ps(out + (x0 + i) * LANES, r[i]);
    }
}

/* returns nothing; on an allocation failure the table's first float is NaN (the caller checks) */
void describe_table(int64_t h, int64_t w, const float *image, int nb, const float *taps, const int *dx, const int *dy,
                    int reach, int K, const float *basis, float floor_, int margin, float *table, int threads) {
    const int64_t wp = w + 2 * reach + 8; /* eight more: a last group of eight pixels reads past the row */
    float *rows = malloc(sizeof(float) * h * w);
    float *padded = malloc(sizeof(float) * h * wp);
    if (rows != NULL && padded != NULL) {
#pragma omp parallel num_threads(threads)
        {
#pragma omp for schedule(static)
            for (int64_t y = 0; y < h; y++) blur_row(image + y * w, w, nb, taps, rows + y * w);
#pragma omp for schedule(static)
            for (int64_t y = 0; y < h; y++) blur_column(rows, h, w, y, nb, taps, reach, padded + y * wp);
#pragma omp for schedule(static)
            for (int64_t y = 0; y < h; y++)
                describe_row(padded, h, w, wp, y, dx, dy, reach, K, basis, floor_, margin, table + y * w * LANES);
        }
    }
    memset(table + h * w * LANES, 0, sizeof(float) * LANES);
    if (rows == NULL || padded == NULL) table[0] = NAN;
    free(rows);
    free(padded);
}
