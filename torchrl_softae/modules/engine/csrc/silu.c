/* SiLU in place, y = x / (1 + exp(-x)), optionally after adding a bias row (y = silu(x + b)), for
 * the ensemble's inference layers (fp32 and bf16).
 *
 * Why: in a bf16 plan on a CPU with AMX, torch's SiLU costs as much as the layer's GEMM and runs no
 * faster in bf16 than in fp32 (it widens to fp32 and calls an accurate vectorized exp); on AMD
 * EPYC with AVX512-BF16 it is 1.5-1.9x slower than this kernel (benchmarks/planning_speed.py
 * --layer-costs, 2 threads). Here exp is 2^k times a polynomial: fp32 results within 1e-6 relative of
 * torch's. bf16 results on AVX-512 use a cheaper form whose fp32 value is within 1e-4 relative
 * (a degree-4 polynomial, a 14-bit reciprocal instead of the division): a bf16 ulp is 4e-3-8e-3
 * relative, so a result differs from torch's in at most one ulp, where the exact value lies next
 * to a rounding boundary. In a loop over values in L1 on one AMX Xeon core it runs at 4.5
 * Gvalues/s against 3.3 for the exact form.
 * The bias (fp32, one value per column) is added in fp32 before the activation: a batched matmul
 * without its bias term plus this pass replaces torch's baddbmm, which copies the broadcast bias
 * into its output before the GEMM (110 against 83 us for a bf16 hidden layer at 206 rows on an
 * AMX CPU).
 *
 * Built at install time as the optional extension torchrl_softae.modules._silu (pyproject.toml);
 * where it does not build, or where it is not faster, the ensemble uses torch's SiLU: the inference
 * path is measured, never assumed (torchrl_softae/modules/engine/paths.py). The instruction set is chosen
 * at run time (AVX512-BF16, AVX-512F, AVX2 with FMA, else portable C), so one build runs on every
 * x86-64 CPU.
 * OpenMP threads: the extension links libgomp.so.1, and imported after torch it shares torch's
 * (same soname), so the kernel runs on torch's own thread pool.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SOFTAE_X86 1
#include "silu_bf16grade.h"
#include "silu_fp32.h"
#endif

enum { DTYPE_FLOAT32 = 0, DTYPE_BFLOAT16 = 1 };

/* ------------------------------------------------------------------ portable C */
static inline float bf16_to_float(uint16_t h) {
    uint32_t u = (uint32_t)h << 16;
    float f;
    memcpy(&f, &u, 4);
    return f;
}

static inline uint16_t float_to_bf16(float f) { /* round to nearest even, NaN stays NaN */
    uint32_t u;
    memcpy(&u, &f, 4);
    if ((u & 0x7fffffffu) > 0x7f800000u) return (uint16_t)((u >> 16) | 0x40u);
    u += 0x7fffu + ((u >> 16) & 1u);
    return (uint16_t)(u >> 16);
}

/* every variant: x[i] = silu(x[i] + b[i]) for i < n, b NULL for no bias */
static void silu_f32_portable(float *x, const float *b, int64_t n) {
    for (int64_t i = 0; i < n; i++) {
        float v = b ? x[i] + b[i] : x[i];
        x[i] = v / (1.0f + expf(-v));
    }
}

static void silu_bf16_portable(uint16_t *x, const float *b, int64_t n) {
    for (int64_t i = 0; i < n; i++) {
        float v = b ? bf16_to_float(x[i]) + b[i] : bf16_to_float(x[i]);
        x[i] = float_to_bf16(v / (1.0f + expf(-v)));
    }
}

/* ------------------------------------------------------------------ AVX2 + FMA */
#ifdef SOFTAE_X86
__attribute__((target("avx2,fma"))) static void silu_f32_avx2(float *x, const float *b, int64_t n) {
    int64_t i = 0;
    if (b)
        for (; i + 8 <= n; i += 8)
            _mm256_storeu_ps(x + i, silu_avx2(_mm256_add_ps(_mm256_loadu_ps(x + i), _mm256_loadu_ps(b + i))));
    else
        for (; i + 8 <= n; i += 8) _mm256_storeu_ps(x + i, silu_avx2(_mm256_loadu_ps(x + i)));
    if (i < n) silu_f32_portable(x + i, b ? b + i : NULL, n - i);
}

/* round to nearest even in integers, as the AVX-512 variant without AVX512-BF16 */
__attribute__((target("avx2,fma"))) static void silu_bf16_avx2(uint16_t *x, const float *b, int64_t n) {
    int64_t i = 0;
    for (; i + 16 <= n; i += 16) {
        __m256i h = _mm256_loadu_si256((const __m256i *)(x + i));
        __m256i out[2];
        for (int half = 0; half < 2; half++) {
            __m128i part = half ? _mm256_extracti128_si256(h, 1) : _mm256_castsi256_si128(h);
            __m256 v = _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_cvtepu16_epi32(part), 16));
            if (b) v = _mm256_add_ps(v, _mm256_loadu_ps(b + i + 8 * half));
            __m256i u = _mm256_castps_si256(silu_avx2(v));
            __m256i lsb = _mm256_and_si256(_mm256_srli_epi32(u, 16), _mm256_set1_epi32(1));
            u = _mm256_add_epi32(u, _mm256_add_epi32(lsb, _mm256_set1_epi32(0x7fff)));
            out[half] = _mm256_srli_epi32(u, 16);
        }
        /* packus works within 128-bit lanes: restore the order with a 64-bit permute */
        __m256i packed = _mm256_permute4x64_epi64(_mm256_packus_epi32(out[0], out[1]), 0xd8);
        _mm256_storeu_si256((__m256i *)(x + i), packed);
    }
    if (i < n) silu_bf16_portable(x + i, b ? b + i : NULL, n - i);
}
#endif

/* ------------------------------------------------------------------ AVX-512 */
#ifdef SOFTAE_X86
__attribute__((target("avx512f"))) static void silu_f32_avx512(float *x, const float *b, int64_t n) {
    int64_t i = 0;
    if (b)
        for (; i + 16 <= n; i += 16)
            _mm512_storeu_ps(x + i, silu_avx512(_mm512_add_ps(_mm512_loadu_ps(x + i), _mm512_loadu_ps(b + i))));
    else
        for (; i + 16 <= n; i += 16) _mm512_storeu_ps(x + i, silu_avx512(_mm512_loadu_ps(x + i)));
    if (i < n) {
        __mmask16 m = (__mmask16)((1u << (n - i)) - 1u);
        __m512 v = _mm512_maskz_loadu_ps(m, x + i);
        if (b) v = _mm512_add_ps(v, _mm512_maskz_loadu_ps(m, b + i));
        _mm512_mask_storeu_ps(x + i, m, silu_avx512(v));
    }
}

__attribute__((target("avx512f,avx512bw"))) static inline __m512 bf16x16_to_f32(__m256i h) {
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(h), 16));
}

/* bf16x16 -> fp32, plus the bias */
__attribute__((target("avx512f,avx512bw,avx512vl"))) static inline __m512 bf16_input(const uint16_t *x, const float *b,
                                                                            __mmask16 m) {
    __m512 v = bf16x16_to_f32(_mm256_maskz_loadu_epi16(m, x));
    return b ? _mm512_add_ps(v, _mm512_maskz_loadu_ps(m, b)) : v;
}

/* without AVX512-BF16: round to nearest even in integers (NaN inputs give NaN through x) */
__attribute__((target("avx512f,avx512bw,avx512vl"))) static inline __m256i f32_to_bf16_avx512(__m512 y) {
    __m512i u = _mm512_castps_si512(y);
    __m512i lsb = _mm512_and_si512(_mm512_srli_epi32(u, 16), _mm512_set1_epi32(1));
    u = _mm512_add_epi32(u, _mm512_add_epi32(lsb, _mm512_set1_epi32(0x7fff)));
    return _mm512_cvtepi32_epi16(_mm512_srli_epi32(u, 16));
}

__attribute__((target("avx512f,avx512bw,avx512vl"))) static void silu_bf16_avx512(uint16_t *x, const float *b, int64_t n) {
    for (int64_t i = 0; i < n; i += 16) {
        __mmask16 m = n - i >= 16 ? (__mmask16)0xffff : (__mmask16)((1u << (n - i)) - 1u);
        __m512 y = silu_bf16grade_avx512(bf16_input(x + i, b ? b + i : NULL, m));
        _mm256_mask_storeu_epi16(x + i, m, f32_to_bf16_avx512(y));
    }
}

/* with AVX512-BF16: the CPU's own round-to-nearest-even conversion (2x fewer instructions) */
__attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16"))) static void silu_bf16_avx512bf16(uint16_t *x, const float *b,
                                                                                         int64_t n) {
    for (int64_t i = 0; i < n; i += 16) {
        __mmask16 m = n - i >= 16 ? (__mmask16)0xffff : (__mmask16)((1u << (n - i)) - 1u);
        __m256bh o = _mm512_cvtneps_pbh(silu_bf16grade_avx512(bf16_input(x + i, b ? b + i : NULL, m)));
        _mm256_mask_storeu_epi16(x + i, m, (__m256i)o);
    }
}
#endif

/* ------------------------------------------------------------------ dispatch */
typedef void (*silu_fn)(void *, const float *, int64_t);
typedef struct {
    const char *name;
    silu_fn f32, bf16;
    int supported;
} variant;

static variant VARIANTS[] = {
    {"portable", (silu_fn)silu_f32_portable, (silu_fn)silu_bf16_portable, 1},
#ifdef SOFTAE_X86
    {"avx2", (silu_fn)silu_f32_avx2, (silu_fn)silu_bf16_avx2, 0},
    {"avx512f", (silu_fn)silu_f32_avx512, (silu_fn)silu_bf16_avx512, 0},
    {"avx512bf16", (silu_fn)silu_f32_avx512, (silu_fn)silu_bf16_avx512bf16, 0},
#endif
};
#define N_VARIANTS ((int)(sizeof(VARIANTS) / sizeof(VARIANTS[0])))
static int CURRENT = 0;

static void detect(void) { /* the best variant this CPU runs, in the order of VARIANTS */
#ifdef SOFTAE_X86
    __builtin_cpu_init();
    /* libgcc's feature bits include the OS check (XCR0) that the AVX-512 state is enabled */
    VARIANTS[1].supported = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    VARIANTS[2].supported = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                            __builtin_cpu_supports("avx512vl");
    VARIANTS[3].supported = VARIANTS[2].supported && __builtin_cpu_supports("avx512bf16");
#endif
    for (int i = 0; i < N_VARIANTS; i++)
        if (VARIANTS[i].supported) CURRENT = i;
}

/* elements of work per thread chunk: large enough that a chunk is not all scheduling */
#define CHUNK ((int64_t)16384)

/* x: `batches` blocks of `rows` rows of `cols` elements; bias (or NULL): `batches` rows of `cols`
 * fp32 values, row `g` added to every row of block `g`. Chunks are whole rows. */
static void silu_parallel(char *x, int64_t batches, int64_t rows, int64_t cols, const float *bias, int dtype,
                          int threads) {
    const int64_t size = dtype == DTYPE_FLOAT32 ? 4 : 2;
    silu_fn fn = dtype == DTYPE_FLOAT32 ? VARIANTS[CURRENT].f32 : VARIANTS[CURRENT].bf16;
    (void)threads;
    if (bias == NULL) { /* no row structure to respect: chunks of CHUNK elements */
        const int64_t n = batches * rows * cols, chunks = (n + CHUNK - 1) / CHUNK;
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1 && chunks > 1)
        for (int64_t c = 0; c < chunks; c++) {
            int64_t start = c * CHUNK;
            fn(x + start * size, NULL, n - start < CHUNK ? n - start : CHUNK);
        }
        return;
    }
    /* whole rows per chunk, each row with its block's bias row */
    const int64_t total = batches * rows, per_chunk = cols >= CHUNK ? 1 : CHUNK / cols;
    const int64_t chunks = (total + per_chunk - 1) / per_chunk;
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1 && chunks > 1)
    for (int64_t c = 0; c < chunks; c++) {
        int64_t last = (c + 1) * per_chunk < total ? (c + 1) * per_chunk : total;
        for (int64_t row = c * per_chunk; row < last; row++)
            fn(x + row * cols * size, bias + (row / rows) * cols, cols);
    }
}

static PyObject *silu_(PyObject *self, PyObject *args) {
    unsigned long long address, bias;
    long long batches, rows, cols;
    int dtype, threads;
    (void)self;
    if (!PyArg_ParseTuple(args, "KLLLKii", &address, &batches, &rows, &cols, &bias, &dtype, &threads)) return NULL;
    if (dtype != DTYPE_FLOAT32 && dtype != DTYPE_BFLOAT16) {
        PyErr_Format(PyExc_ValueError, "silu_: dtype code %d, expected 0 (float32) or 1 (bfloat16)", dtype);
        return NULL;
    }
    if (batches < 0 || rows < 0 || cols < 0 || (batches * rows * cols > 0 && address == 0)) {
        PyErr_Format(PyExc_ValueError, "silu_: %lld x %lld x %lld elements at address %llu", batches, rows, cols,
                     address);
        return NULL;
    }
    if (batches * rows * cols == 0) Py_RETURN_NONE;
    Py_BEGIN_ALLOW_THREADS
    silu_parallel((char *)(uintptr_t)address, (int64_t)batches, (int64_t)rows, (int64_t)cols,
                  (const float *)(uintptr_t)bias, dtype, threads < 1 ? 1 : threads);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

#include "isa_variants.h"

static PyMethodDef METHODS[] = {
    {"silu_", silu_, METH_VARARGS,
     "silu_(address, batches, rows, cols, bias_address, dtype, threads): SiLU in place on batches x rows x cols "
     "contiguous elements (dtype 0 float32, 1 bfloat16), after adding bias row g (fp32, cols values) to every row of "
     "block g where bias_address is not 0"},
    SOFTAE_ISA_METHODS,
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_silu", "SiLU in place (fp32, bf16)", -1, METHODS, NULL, NULL, NULL, NULL};

/* what the kernel computes and how fast: part of the key of inference-path choices cached on disk
 * (torchrl_softae/modules/engine/paths.py), so a choice measured with an older kernel is measured again.
 * 2: the bias row, the bf16 form with a 14-bit reciprocal. */
#define SOFTAE_SILU_REVISION 2

PyMODINIT_FUNC PyInit__silu(void) {
    detect();
    PyObject *module = PyModule_Create(&MODULE);
    if (module != NULL && PyModule_AddIntConstant(module, "REVISION", SOFTAE_SILU_REVISION) < 0) Py_CLEAR(module);
    return module;
}
