/* The guard's local test on a CPU: the median value of each point's nearest neighbours, in C.
 *
 * neighbour_median.py defines which neighbours count: the first k occupied pixels within the
 * radius in ring order (nearest first; equidistant ones by row offset, then column offset),
 * the point itself excluded. Its CPU search is a k-d tree whose last ring is put back into ring
 * order (21-22 ms for 8192 points on one thread, most of the guard's time in a fusion node);
 * here every point walks the ring offsets in an index image and stops at the k-th neighbour,
 * which is that definition read literally. The median is _median_of_rows's: the sorted values'
 * (a[low] + a[high]) / 2 in double, low = (count - 1) / 2, high = count / 2 (NaN with none),
 * so the numbers are the tree's, bit for bit (test/test_fusion_neighbour_median.py).
 *
 * image: (rows, width) point indices (-1: none), bordered by the radius so that every offset
 * from a point stays inside; at: each point's flat position in it; steps: the ring offsets as
 * flat steps (dy * width + dx), nearest first; values: one double per point.
 */
#include <math.h>
#include <stdint.h>

void ring_median(const int32_t *image, const int64_t *at, int64_t n, const int64_t *steps, int64_t nsteps,
                 const double *values, int k, double *median, int64_t *count, int threads) {
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t i = 0; i < n; i++) {
        double taken[256];
        int c = 0;
        for (int64_t s = 0; s < nsteps && c < k; s++) {
            int32_t j = image[at[i] + steps[s]];
            if (j < 0) continue;
            /* insertion into the sorted values taken so far */
            double v = values[j];
            int p = c++;
            while (p > 0 && taken[p - 1] > v) {
                taken[p] = taken[p - 1];
                p--;
            }
            taken[p] = v;
        }
        count[i] = c;
        if (c == 0) {
            median[i] = NAN;
        } else {
            int low = (c - 1) / 2, high = c / 2;
            median[i] = (taken[low] + taken[high]) / 2.0;
        }
    }
}
