/* Eight floats a vector, on any CPU: the AVX2 operations the native kernels use (matching_cost.c,
 * describe_table.c) and the 8x8 transpose that moves between eight pixels' blocks of eight
 * channels and eight planes of eight pixels. native_build digests this header with each kernel
 * that includes it.
 *
 * Where the compiler targets AVX2 and FMA (x86-64 since 2013-2015, built with -mavx2 -mfma) each
 * operation is the AVX2 intrinsic itself. Elsewhere (an ARM robot computer, an x86-64 CPU without
 * AVX2) it is a GCC vector extension, which the compiler lowers to that CPU's vectors (NEON: two
 * registers a vector). Both give the same bits: IEEE arithmetic lane by lane, a written-out FMA
 * rounded once (fmaf), and AVX2's own rules where C has none: a float out of int32's range
 * converts to INT32_MIN, max(a, b) is b when either is NaN, a comparison is false on NaN (the
 * ordered predicates), blendv picks bytes by their top bit. */
#ifndef DEPTH_FUSION_SIMD8_H
#define DEPTH_FUSION_SIMD8_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>

typedef __m256 v8f;
typedef __m256i v8i;
#define V8_CMP_GT _CMP_GT_OQ
#define V8_CMP_LT _CMP_LT_OQ
#define V8_CMP_GE _CMP_GE_OQ
#define v8_set1_ps _mm256_set1_ps
#define v8_setzero_ps _mm256_setzero_ps
#define v8_setr_ps _mm256_setr_ps
#define v8_broadcast_ss _mm256_broadcast_ss
#define v8_loadu_ps _mm256_loadu_ps
#define v8_storeu_ps _mm256_storeu_ps
#define v8_add_ps _mm256_add_ps
#define v8_sub_ps _mm256_sub_ps
#define v8_mul_ps _mm256_mul_ps
#define v8_div_ps _mm256_div_ps
#define v8_fmadd_ps _mm256_fmadd_ps
#define v8_and_ps _mm256_and_ps
#define v8_or_ps _mm256_or_ps
#define v8_max_ps _mm256_max_ps
#define v8_sqrt_ps _mm256_sqrt_ps
#define v8_floor_ps _mm256_floor_ps
#define v8_cmp_ps _mm256_cmp_ps
#define v8_cvttps_epi32 _mm256_cvttps_epi32
#define v8_castps_si256 _mm256_castps_si256
#define v8_set1_epi32 _mm256_set1_epi32
#define v8_add_epi32 _mm256_add_epi32
#define v8_mullo_epi32 _mm256_mullo_epi32
#define v8_storeu_si256 _mm256_storeu_si256
#define v8_blendv_epi8 _mm256_blendv_epi8

/* r[i] lane j becomes r[j] lane i */
static inline void transpose8(v8f *r) {
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

#else

typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
typedef uint32_t v8u __attribute__((vector_size(32)));
typedef int8_t v32b __attribute__((vector_size(32)));
enum { V8_CMP_GT, V8_CMP_LT, V8_CMP_GE };

static inline v8f v8_set1_ps(float a) { return (v8f){a, a, a, a, a, a, a, a}; }
static inline v8f v8_setzero_ps(void) { return v8_set1_ps(0.0f); }
static inline v8f v8_setr_ps(float a, float b, float c, float d, float e, float f, float g, float h) {
    return (v8f){a, b, c, d, e, f, g, h};
}
static inline v8f v8_broadcast_ss(const float *p) { return v8_set1_ps(*p); }
static inline v8f v8_loadu_ps(const float *p) {
    v8f r;
    memcpy(&r, p, sizeof r);
    return r;
}
static inline void v8_storeu_ps(float *p, v8f a) { memcpy(p, &a, sizeof a); }
static inline v8f v8_add_ps(v8f a, v8f b) { return a + b; }
static inline v8f v8_sub_ps(v8f a, v8f b) { return a - b; }
static inline v8f v8_mul_ps(v8f a, v8f b) { return a * b; }
static inline v8f v8_div_ps(v8f a, v8f b) { return a / b; }
static inline v8f v8_fmadd_ps(v8f a, v8f b, v8f c) {
    v8f r;
    for (int j = 0; j < 8; j++) r[j] = fmaf(a[j], b[j], c[j]);
    return r;
}
static inline v8f v8_and_ps(v8f a, v8f b) { return (v8f)((v8i)a & (v8i)b); }
static inline v8f v8_or_ps(v8f a, v8f b) { return (v8f)((v8i)a | (v8i)b); }
static inline v8f v8_max_ps(v8f a, v8f b) {
    v8f r;
    for (int j = 0; j < 8; j++) r[j] = a[j] > b[j] ? a[j] : b[j];
    return r;
}
static inline v8f v8_sqrt_ps(v8f a) {
    v8f r;
    for (int j = 0; j < 8; j++) r[j] = sqrtf(a[j]);
    return r;
}
static inline v8f v8_floor_ps(v8f a) {
    v8f r;
    for (int j = 0; j < 8; j++) r[j] = floorf(a[j]);
    return r;
}
/* All ones where the ordered predicate holds (false on NaN), else zero. */
static inline v8f v8_cmp_ps(v8f a, v8f b, int predicate) {
    v8i m;
    if (predicate == V8_CMP_GT)
        m = a > b;
    else if (predicate == V8_CMP_LT)
        m = a < b;
    else
        m = a >= b;
    return (v8f)m;
}
static inline v8i v8_cvttps_epi32(v8f a) {
    v8i r;
    for (int j = 0; j < 8; j++) r[j] = (a[j] >= -2147483648.0f && a[j] < 2147483648.0f) ? (int32_t)a[j] : INT32_MIN;
    return r;
}
static inline v8i v8_castps_si256(v8f a) { return (v8i)a; }
static inline v8i v8_set1_epi32(int32_t a) { return (v8i){a, a, a, a, a, a, a, a}; }
static inline v8i v8_add_epi32(v8i a, v8i b) { return (v8i)((v8u)a + (v8u)b); }
static inline v8i v8_mullo_epi32(v8i a, v8i b) { return (v8i)((v8u)a * (v8u)b); }
static inline void v8_storeu_si256(v8i *p, v8i a) { memcpy(p, &a, sizeof a); }
/* Each byte of b where the mask byte's top bit is set, else of a. */
static inline v8i v8_blendv_epi8(v8i a, v8i b, v8i mask) {
    v32b m = (v32b)mask >> 7;
    return (v8i)(((v32b)b & m) | ((v32b)a & ~m));
}

/* r[i] lane j becomes r[j] lane i */
static inline void transpose8(v8f *r) {
    float t[8][8];
    for (int i = 0; i < 8; i++)
        for (int j = 0; j < 8; j++) t[j][i] = r[i][j];
    for (int i = 0; i < 8; i++) memcpy(&r[i], t[i], sizeof r[i]);
}

#endif
#endif
