/* The silhouette-halo test of every multi-view point in one pass on a CPU, in C
 * (occlusion.halo_points, its five steps per point; the image-level work stays in numpy and OpenCV).
 *
 * In numpy each step is a few dozen whole-array operations over the points (16-20 thousand of them
 * at 320x240): the gradient direction, seven bilinear samples of the gradient magnitude along it
 * (cv2.remap), the peak and its parabola, four samples of the single-view log depth, the tests, and
 * for the candidates eighteen samples of the points beyond, sorted for their median: 6-12 ms a
 * keyframe, a tenth of the fusion node's. Here one loop per point does the same, every operation
 * numpy's in its order and float32 rounding (built with -ffp-contract=off): OpenCV's remap with
 * float maps is the bilinear read fma(bottom - top, fy, top) of the rows' fma(b - a, fx, a), the
 * border pixels repeated; np.argmax takes the first largest (the first NaN if any); np.rint rounds
 * half to even as rintf does; the median of the beyond samples is that of the sorted finite ones
 * (an insertion sort of at most eighteen).
 * The same halos bit for bit (test/test_native_halo.py).
 *
 * mag, gx, gy (h, w): the blurred image's gradient magnitude and Sobel derivatives; filled (h, w):
 * the single-view log depth, its holes filled; n points at rows, cols with multi-view log depth
 * log_m; scale the median log ratio of the points to the single view; min_step the least step;
 * search_px, side_px, near_share, beyond_from and beyond_to occlusion.py's constants; out (n,)
 * bytes: 1 in a halo. Points split over threads: each is computed alone.
 */
#include <math.h>
#include <stdint.h>

/* the most the caller may ask for (native_halo.py checks): the search's half-length and the
 * steps beyond (occlusion.py's SEARCH_PX and BEYOND_PX, handed over with SIDE_PX and NEAR_SHARE so
 * that they are written once) */
#define MAX_SEARCH_PX 32
#define MAX_BEYOND_STEPS 64

static inline int64_t clamp_index(int64_t v, int64_t high) { return v < 0 ? 0 : (v > high ? high : v); }

/* cv2.remap's INTER_LINEAR read of a float image at (x, y), border pixels repeated */
static inline float bilinear(const float *img, int64_t h, int64_t w, float x, float y) {
    const float x0 = floorf(x), y0 = floorf(y);
    const float fx = x - x0, fy = y - y0;
    /* a coordinate too far outside for an integer (or NaN) is read at a border, as any far one is */
    const int64_t xi = !(x0 >= -1.0f) ? -1 : ((x0 > (float)w) ? w : (int64_t)x0);
    const int64_t yi = !(y0 >= -1.0f) ? -1 : ((y0 > (float)h) ? h : (int64_t)y0);
    const int64_t c0 = clamp_index(xi, w - 1), c1 = clamp_index(xi + 1, w - 1);
    const float *r0 = img + clamp_index(yi, h - 1) * w, *r1 = img + clamp_index(yi + 1, h - 1) * w;
    const float top = fmaf(r0[c1] - r0[c0], fx, r0[c0]);
    const float bottom = fmaf(r1[c1] - r1[c0], fx, r1[c0]);
    return fmaf(bottom - top, fy, top);
}

/* _edge_offsets at one point: the unit gradient direction and the sub-pixel offset of the
 * magnitude's peak within +-search px along it */
static void edge_offset(const float *mag, const float *gx, const float *gy, int64_t h, int64_t w, int64_t at,
                        float x, float y, int search, float *nx, float *ny, float *peak) {
    float norm = mag[at];
    norm = (norm != norm) ? norm : (norm > 1e-6f ? norm : 1e-6f); /* np.maximum keeps a NaN */
    const float ux = gx[at] / norm, uy = gy[at] / norm;
    float s[2 * MAX_SEARCH_PX + 1];
    int j = 0;
    for (int k = 0; k <= 2 * search; k++) {
        const float step = (float)(k - search);
        s[k] = bilinear(mag, h, w, x + step * ux, y + step * uy);
    }
    for (int k = 1; k <= 2 * search; k++) { /* np.argmax: the first largest, or the first NaN */
        if (s[j] != s[j]) break;
        if (s[k] != s[k] || s[k] > s[j]) j = k;
    }
    j = j < 1 ? 1 : (j > 2 * search - 1 ? 2 * search - 1 : j);
    const float left = s[j - 1], centre = s[j], right = s[j + 1];
    const float curvature = (left - 2.0f * centre) + right;
    const int peaked = curvature < -1e-9f;
    float delta = peaked ? (0.5f * (left - right)) / curvature : 0.0f;
    delta = (delta != delta) ? delta : (delta < -1.0f ? -1.0f : (delta > 1.0f ? 1.0f : delta));
    *nx = ux;
    *ny = uy;
    *peak = (float)(j - search) + delta;
}

/* _beyond_agrees at one candidate */
static int beyond_agrees(const float *log_points, int64_t h, int64_t w, float x, float y, float nx, float ny,
                         int grows, float log_m, float far_log, int from, int to) {
    const float sign = grows ? 1.0f : -1.0f;
    float samples[3 * MAX_BEYOND_STEPS];
    int n = 0;
    for (int t = from; t <= to; t++) {
        const float along = sign * (float)t;
        for (int l = -1; l <= 1; l++) {
            const float lateral = (float)l;
            const float xs = (x + along * nx) - lateral * ny;
            const float ys = (y + along * ny) + lateral * nx;
            const float rx = rintf(xs), ry = rintf(ys); /* (NaN or far: a border, not undefined) */
            const int64_t xi = !(rx >= 0.0f) ? 0 : (rx >= (float)w ? w - 1 : (int64_t)rx);
            const int64_t yi = !(ry >= 0.0f) ? 0 : (ry >= (float)h ? h - 1 : (int64_t)ry);
            const float v = log_points[yi * w + xi];
            if (!isfinite(v)) continue; /* np.sort puts them last, past the median's reach */
            int k = n++; /* insertion sort of the finite samples, ascending */
            for (; k > 0 && samples[k - 1] > v; k--) samples[k] = samples[k - 1];
            samples[k] = v;
        }
    }
    if (n < 2) return 0;
    const float beyond = 0.5f * (samples[(n - 1) / 2] + samples[n / 2]);
    return fabsf(beyond - log_m) < fabsf(beyond - far_log);
}

void halo_test(int64_t h, int64_t w, const float *mag, const float *gx, const float *gy, const float *filled,
               const float *log_points, int64_t n, const int64_t *rows, const int64_t *cols, const float *log_m,
               float scale, float min_step, int search_px, float side_px, float near_share, int beyond_from,
               int beyond_to, uint8_t *out, int threads) {
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t i = 0; i < n; i++) {
        const int64_t at = rows[i] * w + cols[i];
        const float x = (float)cols[i], y = (float)rows[i];
        float nx, ny, peak;
        edge_offset(mag, gx, gy, h, w, at, x, y, search_px, &nx, &ny, &peak);
        /* _single_view_sides: the single view at +-side_px and +-2 side_px along n */
        const float side = side_px, far_side = 2.0f * side_px;
        const float plus = bilinear(filled, h, w, x + side * nx, y + side * ny);
        const float minus = bilinear(filled, h, w, x + -side * nx, y + -side * ny);
        const float plus2 = bilinear(filled, h, w, x + far_side * nx, y + far_side * ny);
        const float minus2 = bilinear(filled, h, w, x + -far_side * nx, y + -far_side * ny);
        const float diff = plus - minus;
        const float sign = (diff != diff) ? diff : (float)((diff > 0.0f) - (diff < 0.0f));
        const float ramp = sign * ((plus2 - plus) + (minus - minus2));
        const int nan = (plus != plus) || (minus != minus);
        const float near = nan ? NAN : (plus < minus ? plus : minus);
        const float far = nan ? NAN : (plus > minus ? plus : minus);
        const int grows = plus > minus;
        const float step = far - near;
        const float offset = grows ? -peak : peak;
        int halo = ((step - ramp) > min_step) && (offset > 0.0f);
        halo = halo && ((log_m[i] - scale) < near + near_share * step);
        if (halo && beyond_agrees(log_points, h, w, x, y, nx, ny, grows, log_m[i], far + scale, beyond_from, beyond_to))
            halo = 0;
        out[i] = (uint8_t)halo;
    }
}
