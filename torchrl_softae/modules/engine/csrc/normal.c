/* Standard normal draws for planning, counter-based and multi-threaded: out[i] = x[i] + s[i] * z_i
 * (or z_i alone), z_i ~ N(0, 1).
 *
 * Why: torch's CPU generator (mt19937) draws about one normal value per 2.5 ns on one thread; in a
 * bf16 10-particle arm plan on the AMX Xeon the aleatoric noise draws (normal_, 15 ms of 170) were
 * the largest op after the network. Here each value is a pure function of (seed, index): a
 * SplitMix64 output of the counter gives two 24-bit uniforms, Box-Muller turns them into two
 * normals, and any thread can compute any block, so results do not depend on the thread count.
 *
 * The stream, for one seed (one 64-bit value drawn from the caller's torch.Generator per call):
 *   pair j:  h = mix64(seed + (j + 1) * 0x9E3779B97F4A7C15)          (SplitMix64)
 *            u1 = (h >> 40) + 1) / 2^24 in (0, 1],  u2 = ((h >> 16) & 0xFFFFFF) / 2^24 in [0, 1)
 *            r = sqrt(-2 log u1), theta = 2 pi u2
 *   values in blocks of 32: block b holds pairs 16 b .. 16 b + 15, first their r cos(theta), then
 *   their r sin(theta). |z| <= sqrt(-2 log 2^-24) = 5.77.
 * log and sin/cos are polynomials in fp32 (below, about 1e-7 relative), evaluated in the same
 * order with the same fused multiply-adds in every variant (AVX-512, AVX2 with FMA, portable C with
 * fmaf), so every variant gives the same bits. The portable one (a libm call per fmaf) is for other
 * architectures: about 10x slower than the vector ones.
 *
 * Built at install time as the optional extension torchrl_softae.modules._normal (pyproject.toml);
 * OpenMP threads are torch's own (see silu.c).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SOFTAE_X86 1
#endif

#define GOLDEN 0x9E3779B97F4A7C15ull
#define PAIRS 16 /* pairs per block: a block is 32 values */

/* the polynomial coefficients, one list for every variant */
#define LN2 0.693147180559945309f
#define TWO_PI_QUARTER 1.57079632679489662f /* 2 pi / 4: a quarter turn */
#define SQRT2 1.41421356237309505f
/* log(m) = 2 f (1 + f^2/3 + f^4/5 + f^6/7 + f^8/9), f = (m - 1) / (m + 1), m in [sqrt(1/2), sqrt(2)) */
#define L9 (1.0f / 9.0f)
#define L7 (1.0f / 7.0f)
#define L5 (1.0f / 5.0f)
#define L3 (1.0f / 3.0f)
/* on x in [-pi/4, pi/4]: sin x = x (1 - x^2/6 + x^4/120 - x^6/5040 + x^8/362880),
 * cos x = 1 - x^2/2 + x^4/24 - x^6/720 + x^8/40320 */
#define S9 (1.0f / 362880.0f)
#define S7 (-1.0f / 5040.0f)
#define S5 (1.0f / 120.0f)
#define S3 (-1.0f / 6.0f)
#define C8 (1.0f / 40320.0f)
#define C6 (-1.0f / 720.0f)
#define C4 (1.0f / 24.0f)
#define C2 (-0.5f)

static inline uint64_t mix64(uint64_t z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

/* ------------------------------------------------------------------ portable C */
static void block_portable(uint64_t seed, int64_t block, float *z) {
    for (int j = 0; j < PAIRS; j++) {
        const uint64_t h = mix64(seed + (uint64_t)(block * PAIRS + j + 1) * GOLDEN);
        const float u1 = (float)((h >> 40) + 1) * 0x1p-24f, u2 = (float)((h >> 16) & 0xFFFFFFu) * 0x1p-24f;
        /* log u1 = e ln2 + log m */
        uint32_t bits;
        memcpy(&bits, &u1, 4);
        int e = (int)(bits >> 23) - 127;
        uint32_t mb = (bits & 0x7FFFFFu) | 0x3F800000u;
        float m;
        memcpy(&m, &mb, 4);
        if (m > SQRT2) {
            m = m * 0.5f;
            e += 1;
        }
        const float f = (m - 1.0f) / (m + 1.0f), f2 = f * f;
        float p = fmaf(L9, f2, L7);
        p = fmaf(p, f2, L5);
        p = fmaf(p, f2, L3);
        p = fmaf(p, f2, 1.0f);
        const float log_u1 = fmaf((float)e, LN2, (f + f) * p);
        const float r = sqrtf(-2.0f * log_u1);
        /* theta = 2 pi u2 = q quarter turns + x, |x| <= pi/4 */
        const float q = rintf(u2 * 4.0f);
        const float x = (u2 * 4.0f - q) * TWO_PI_QUARTER, x2 = x * x;
        float s = fmaf(S9, x2, S7);
        s = fmaf(s, x2, S5);
        s = fmaf(s, x2, S3);
        s = fmaf(s * x2, x, x);
        float c = fmaf(C8, x2, C6);
        c = fmaf(c, x2, C4);
        c = fmaf(c, x2, C2);
        c = fmaf(c, x2, 1.0f);
        const int quadrant = (int)q & 3;
        const float cos_t = quadrant == 0 ? c : quadrant == 1 ? -s : quadrant == 2 ? -c : s;
        const float sin_t = quadrant == 0 ? s : quadrant == 1 ? c : quadrant == 2 ? -s : -c;
        z[j] = r * cos_t;
        z[PAIRS + j] = r * sin_t;
    }
}

/* ------------------------------------------------------------------ AVX-512 (F, DQ) */
#ifdef SOFTAE_X86
__attribute__((target("avx512f,avx512dq"))) static inline __m512i mix64_avx512(__m512i z) {
    z = _mm512_mullo_epi64(_mm512_xor_si512(z, _mm512_srli_epi64(z, 30)), _mm512_set1_epi64((long long)0xBF58476D1CE4E5B9ull));
    z = _mm512_mullo_epi64(_mm512_xor_si512(z, _mm512_srli_epi64(z, 27)), _mm512_set1_epi64((long long)0x94D049BB133111EBull));
    return _mm512_xor_si512(z, _mm512_srli_epi64(z, 31));
}

__attribute__((target("avx512f,avx512dq"))) static void block_avx512(uint64_t seed, int64_t block, float *z) {
    /* 16 pairs: two vectors of 8 64-bit hashes, narrowed to one vector of 16 32-bit fields each */
    const __m512i lanes = _mm512_setr_epi64(1, 2, 3, 4, 5, 6, 7, 8);
    const __m512i base = _mm512_set1_epi64((long long)(block * PAIRS));
    const __m512i golden = _mm512_set1_epi64((long long)GOLDEN), s = _mm512_set1_epi64((long long)seed);
    __m512i h0 = mix64_avx512(_mm512_add_epi64(s, _mm512_mullo_epi64(_mm512_add_epi64(base, lanes), golden)));
    __m512i h1 = mix64_avx512(_mm512_add_epi64(
        s, _mm512_mullo_epi64(_mm512_add_epi64(base, _mm512_add_epi64(lanes, _mm512_set1_epi64(8))), golden)));
    const __m512i k1 = _mm512_inserti64x4(_mm512_castsi256_si512(_mm512_cvtepi64_epi32(_mm512_srli_epi64(h0, 40))),
                                          _mm512_cvtepi64_epi32(_mm512_srli_epi64(h1, 40)), 1);
    const __m512i k2 = _mm512_and_si512(
        _mm512_inserti64x4(_mm512_castsi256_si512(_mm512_cvtepi64_epi32(_mm512_srli_epi64(h0, 16))),
                           _mm512_cvtepi64_epi32(_mm512_srli_epi64(h1, 16)), 1),
        _mm512_set1_epi32(0xFFFFFF));
    const __m512 u1 = _mm512_mul_ps(_mm512_cvtepi32_ps(_mm512_add_epi32(k1, _mm512_set1_epi32(1))), _mm512_set1_ps(0x1p-24f));
    const __m512 u2 = _mm512_mul_ps(_mm512_cvtepi32_ps(k2), _mm512_set1_ps(0x1p-24f));
    /* log u1 */
    const __m512i bits = _mm512_castps_si512(u1);
    __m512 e = _mm512_cvtepi32_ps(_mm512_sub_epi32(_mm512_srli_epi32(bits, 23), _mm512_set1_epi32(127)));
    __m512 m = _mm512_castsi512_ps(
        _mm512_or_si512(_mm512_and_si512(bits, _mm512_set1_epi32(0x7FFFFF)), _mm512_set1_epi32(0x3F800000)));
    const __mmask16 big = _mm512_cmp_ps_mask(m, _mm512_set1_ps(SQRT2), _CMP_GT_OQ);
    m = _mm512_mask_mul_ps(m, big, m, _mm512_set1_ps(0.5f));
    e = _mm512_mask_add_ps(e, big, e, _mm512_set1_ps(1.0f));
    const __m512 one = _mm512_set1_ps(1.0f);
    const __m512 f = _mm512_div_ps(_mm512_sub_ps(m, one), _mm512_add_ps(m, one)), f2 = _mm512_mul_ps(f, f);
    __m512 p = _mm512_fmadd_ps(_mm512_set1_ps(L9), f2, _mm512_set1_ps(L7));
    p = _mm512_fmadd_ps(p, f2, _mm512_set1_ps(L5));
    p = _mm512_fmadd_ps(p, f2, _mm512_set1_ps(L3));
    p = _mm512_fmadd_ps(p, f2, one);
    const __m512 log_u1 = _mm512_fmadd_ps(e, _mm512_set1_ps(LN2), _mm512_mul_ps(_mm512_add_ps(f, f), p));
    const __m512 r = _mm512_sqrt_ps(_mm512_mul_ps(_mm512_set1_ps(-2.0f), log_u1));
    /* sin and cos */
    const __m512 t = _mm512_mul_ps(u2, _mm512_set1_ps(4.0f));
    const __m512 q = _mm512_roundscale_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m512 x = _mm512_mul_ps(_mm512_sub_ps(t, q), _mm512_set1_ps(TWO_PI_QUARTER)), x2 = _mm512_mul_ps(x, x);
    __m512 sn = _mm512_fmadd_ps(_mm512_set1_ps(S9), x2, _mm512_set1_ps(S7));
    sn = _mm512_fmadd_ps(sn, x2, _mm512_set1_ps(S5));
    sn = _mm512_fmadd_ps(sn, x2, _mm512_set1_ps(S3));
    sn = _mm512_fmadd_ps(_mm512_mul_ps(sn, x2), x, x);
    __m512 cs = _mm512_fmadd_ps(_mm512_set1_ps(C8), x2, _mm512_set1_ps(C6));
    cs = _mm512_fmadd_ps(cs, x2, _mm512_set1_ps(C4));
    cs = _mm512_fmadd_ps(cs, x2, _mm512_set1_ps(C2));
    cs = _mm512_fmadd_ps(cs, x2, one);
    const __m512i quadrant = _mm512_and_si512(_mm512_cvtps_epi32(q), _mm512_set1_epi32(3));
    const __mmask16 odd = _mm512_test_epi32_mask(quadrant, _mm512_set1_epi32(1));
    /* quadrants 1 and 3 swap sin and cos; the signs: cos < 0 in 1 (as -s) and 2, sin < 0 in 2 and 3 */
    __m512 cos_t = _mm512_mask_blend_ps(odd, cs, sn), sin_t = _mm512_mask_blend_ps(odd, sn, cs);
    const __mmask16 cos_neg = _mm512_cmpeq_epi32_mask(quadrant, _mm512_set1_epi32(1)) |
                              _mm512_cmpeq_epi32_mask(quadrant, _mm512_set1_epi32(2));
    const __mmask16 sin_neg = _mm512_cmpge_epi32_mask(quadrant, _mm512_set1_epi32(2));
    const __m512 sign = _mm512_set1_ps(-0.0f); /* flipping the sign bit, as the portable -s does */
    cos_t = _mm512_mask_xor_ps(cos_t, cos_neg, cos_t, sign);
    sin_t = _mm512_mask_xor_ps(sin_t, sin_neg, sin_t, sign);
    _mm512_storeu_ps(z, _mm512_mul_ps(r, cos_t));
    _mm512_storeu_ps(z + PAIRS, _mm512_mul_ps(r, sin_t));
}

/* ------------------------------------------------------------------ AVX2 with FMA
 * The same arithmetic on 8 lanes, twice per block; AVX2 has no 64-bit multiply, so it is built
 * from three 32 x 32 -> 64-bit ones (the products that reach the low 64 bits). */
__attribute__((target("avx2,fma"))) static inline __m256i mullo64_avx2(__m256i a, __m256i b) {
    const __m256i cross = _mm256_add_epi64(_mm256_mul_epu32(_mm256_srli_epi64(a, 32), b),
                                           _mm256_mul_epu32(a, _mm256_srli_epi64(b, 32)));
    return _mm256_add_epi64(_mm256_mul_epu32(a, b), _mm256_slli_epi64(cross, 32));
}

__attribute__((target("avx2,fma"))) static inline __m256i mix64_avx2(__m256i z) {
    z = mullo64_avx2(_mm256_xor_si256(z, _mm256_srli_epi64(z, 30)), _mm256_set1_epi64x((long long)0xBF58476D1CE4E5B9ull));
    z = mullo64_avx2(_mm256_xor_si256(z, _mm256_srli_epi64(z, 27)), _mm256_set1_epi64x((long long)0x94D049BB133111EBull));
    return _mm256_xor_si256(z, _mm256_srli_epi64(z, 31));
}

/* the low 32 bits of the eight 64-bit lanes of a and b, in order */
__attribute__((target("avx2,fma"))) static inline __m256i narrow_avx2(__m256i a, __m256i b) {
    const __m256i low = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
    return _mm256_permute2x128_si256(_mm256_permutevar8x32_epi32(a, low), _mm256_permutevar8x32_epi32(b, low), 0x20);
}

__attribute__((target("avx2,fma"))) static void block_avx2(uint64_t seed, int64_t block, float *z) {
    const __m256i golden = _mm256_set1_epi64x((long long)GOLDEN), s = _mm256_set1_epi64x((long long)seed);
    const __m256 one = _mm256_set1_ps(1.0f);
    for (int half = 0; half < 2; half++) {
        const long long first = block * PAIRS + half * 8 + 1;
        const __m256i c0 = _mm256_setr_epi64x(first, first + 1, first + 2, first + 3);
        const __m256i c1 = _mm256_add_epi64(c0, _mm256_set1_epi64x(4));
        const __m256i h0 = mix64_avx2(_mm256_add_epi64(s, mullo64_avx2(c0, golden)));
        const __m256i h1 = mix64_avx2(_mm256_add_epi64(s, mullo64_avx2(c1, golden)));
        const __m256i k1 = narrow_avx2(_mm256_srli_epi64(h0, 40), _mm256_srli_epi64(h1, 40));
        const __m256i k2 = _mm256_and_si256(narrow_avx2(_mm256_srli_epi64(h0, 16), _mm256_srli_epi64(h1, 16)),
                                            _mm256_set1_epi32(0xFFFFFF));
        const __m256 u1 = _mm256_mul_ps(_mm256_cvtepi32_ps(_mm256_add_epi32(k1, _mm256_set1_epi32(1))), _mm256_set1_ps(0x1p-24f));
        const __m256 u2 = _mm256_mul_ps(_mm256_cvtepi32_ps(k2), _mm256_set1_ps(0x1p-24f));
        const __m256i bits = _mm256_castps_si256(u1);
        __m256 e = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(bits, 23), _mm256_set1_epi32(127)));
        __m256 m = _mm256_castsi256_ps(
            _mm256_or_si256(_mm256_and_si256(bits, _mm256_set1_epi32(0x7FFFFF)), _mm256_set1_epi32(0x3F800000)));
        const __m256 big = _mm256_cmp_ps(m, _mm256_set1_ps(SQRT2), _CMP_GT_OQ);
        m = _mm256_blendv_ps(m, _mm256_mul_ps(m, _mm256_set1_ps(0.5f)), big);
        e = _mm256_blendv_ps(e, _mm256_add_ps(e, one), big);
        const __m256 f = _mm256_div_ps(_mm256_sub_ps(m, one), _mm256_add_ps(m, one)), f2 = _mm256_mul_ps(f, f);
        __m256 p = _mm256_fmadd_ps(_mm256_set1_ps(L9), f2, _mm256_set1_ps(L7));
        p = _mm256_fmadd_ps(p, f2, _mm256_set1_ps(L5));
        p = _mm256_fmadd_ps(p, f2, _mm256_set1_ps(L3));
        p = _mm256_fmadd_ps(p, f2, one);
        const __m256 log_u1 = _mm256_fmadd_ps(e, _mm256_set1_ps(LN2), _mm256_mul_ps(_mm256_add_ps(f, f), p));
        const __m256 r = _mm256_sqrt_ps(_mm256_mul_ps(_mm256_set1_ps(-2.0f), log_u1));
        const __m256 t = _mm256_mul_ps(u2, _mm256_set1_ps(4.0f));
        const __m256 q = _mm256_round_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
        const __m256 x = _mm256_mul_ps(_mm256_sub_ps(t, q), _mm256_set1_ps(TWO_PI_QUARTER)), x2 = _mm256_mul_ps(x, x);
        __m256 sn = _mm256_fmadd_ps(_mm256_set1_ps(S9), x2, _mm256_set1_ps(S7));
        sn = _mm256_fmadd_ps(sn, x2, _mm256_set1_ps(S5));
        sn = _mm256_fmadd_ps(sn, x2, _mm256_set1_ps(S3));
        sn = _mm256_fmadd_ps(_mm256_mul_ps(sn, x2), x, x);
        __m256 cs = _mm256_fmadd_ps(_mm256_set1_ps(C8), x2, _mm256_set1_ps(C6));
        cs = _mm256_fmadd_ps(cs, x2, _mm256_set1_ps(C4));
        cs = _mm256_fmadd_ps(cs, x2, _mm256_set1_ps(C2));
        cs = _mm256_fmadd_ps(cs, x2, one);
        const __m256i quadrant = _mm256_and_si256(_mm256_cvtps_epi32(q), _mm256_set1_epi32(3));
        const __m256 odd = _mm256_castsi256_ps(
            _mm256_cmpeq_epi32(_mm256_and_si256(quadrant, _mm256_set1_epi32(1)), _mm256_set1_epi32(1)));
        __m256 cos_t = _mm256_blendv_ps(cs, sn, odd), sin_t = _mm256_blendv_ps(sn, cs, odd);
        const __m256 sign = _mm256_set1_ps(-0.0f);
        const __m256 cos_neg = _mm256_castsi256_ps(_mm256_or_si256(_mm256_cmpeq_epi32(quadrant, _mm256_set1_epi32(1)),
                                                                   _mm256_cmpeq_epi32(quadrant, _mm256_set1_epi32(2))));
        const __m256 sin_neg = _mm256_castsi256_ps(_mm256_cmpgt_epi32(quadrant, _mm256_set1_epi32(1)));
        cos_t = _mm256_xor_ps(cos_t, _mm256_and_ps(cos_neg, sign));
        sin_t = _mm256_xor_ps(sin_t, _mm256_and_ps(sin_neg, sign));
        _mm256_storeu_ps(z + half * 8, _mm256_mul_ps(r, cos_t));
        _mm256_storeu_ps(z + PAIRS + half * 8, _mm256_mul_ps(r, sin_t));
    }
}
#endif

/* ------------------------------------------------------------------ dispatch */
typedef void (*block_fn)(uint64_t, int64_t, float *);
typedef struct {
    const char *name;
    block_fn block;
    int supported;
} variant;

static variant VARIANTS[] = {
    {"portable", block_portable, 1},
#ifdef SOFTAE_X86
    {"avx2", block_avx2, 0},
    {"avx512", block_avx512, 0},
#endif
};
#define N_VARIANTS ((int)(sizeof(VARIANTS) / sizeof(VARIANTS[0])))
static int CURRENT = 0;

static void detect(void) {
#ifdef SOFTAE_X86
    __builtin_cpu_init();
    VARIANTS[1].supported = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    VARIANTS[2].supported = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq");
#endif
    for (int i = 0; i < N_VARIANTS; i++)
        if (VARIANTS[i].supported) CURRENT = i;
}

/* blocks per thread chunk: large enough that a chunk is not all scheduling */
#define CHUNK_BLOCKS ((int64_t)512)

/* out[i] = (x ? x[i] : 0) + (s ? s[i] : 1) * z_i for i < n */
static void fill(float *out, const float *x, const float *s, int64_t n, uint64_t seed, int threads) {
    const block_fn block = VARIANTS[CURRENT].block;
    const int64_t blocks = (n + 2 * PAIRS - 1) / (2 * PAIRS), chunks = (blocks + CHUNK_BLOCKS - 1) / CHUNK_BLOCKS;
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1 && chunks > 1)
    for (int64_t c = 0; c < chunks; c++) {
        float z[2 * PAIRS];
        const int64_t last = (c + 1) * CHUNK_BLOCKS < blocks ? (c + 1) * CHUNK_BLOCKS : blocks;
        for (int64_t b = c * CHUNK_BLOCKS; b < last; b++) {
            block(seed, b, z);
            const int64_t start = b * 2 * PAIRS, count = n - start < 2 * PAIRS ? n - start : 2 * PAIRS;
            for (int64_t i = 0; i < count; i++) {
                const float v = s ? s[start + i] * z[i] : z[i];
                out[start + i] = x ? x[start + i] + v : v;
            }
        }
    }
}

static PyObject *py_fill(PyObject *self, PyObject *args) {
    unsigned long long out, x, s, seed;
    long long n;
    int threads;
    (void)self;
    if (!PyArg_ParseTuple(args, "KKKLKi", &out, &x, &s, &n, &seed, &threads)) return NULL;
    if (n < 0 || (n > 0 && out == 0)) {
        PyErr_Format(PyExc_ValueError, "normal.fill: %lld values at address %llu", n, out);
        return NULL;
    }
    if (n == 0) Py_RETURN_NONE;
    Py_BEGIN_ALLOW_THREADS
    fill((float *)(uintptr_t)out, (const float *)(uintptr_t)x, (const float *)(uintptr_t)s, (int64_t)n, (uint64_t)seed,
         threads < 1 ? 1 : threads);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

#include "isa_variants.h"

static PyMethodDef METHODS[] = {
    {"fill", py_fill, METH_VARARGS,
     "fill(out, x, s, n, seed, threads): out[i] = x[i] + s[i] * z_i, z_i ~ N(0, 1) the stream of seed "
     "(addresses of contiguous float32 buffers; x or s 0 for none)"},
    SOFTAE_ISA_METHODS,
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_normal", "counter-based normal draws", -1, METHODS,
                                    NULL, NULL, NULL, NULL};

/* the stream's definition: a new revision draws other values for the same seed */
#define SOFTAE_NORMAL_REVISION 1

PyMODINIT_FUNC PyInit__normal(void) {
    detect();
    PyObject *module = PyModule_Create(&MODULE);
    if (module != NULL && PyModule_AddIntConstant(module, "REVISION", SOFTAE_NORMAL_REVISION) < 0) Py_CLEAR(module);
    return module;
}
