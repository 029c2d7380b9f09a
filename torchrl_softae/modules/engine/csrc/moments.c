/* The ensemble's moments in one pass over its raw output, for planning (fp32 or bf16 input).
 *
 * For each row n and state dimension j, from the normalized member deltas y_l (the last layer's
 * output, in the planner's dtype) and the state s:
 *     m_l   = (s + loc) + scale * y_l                        member means       (l = 0..L-1)
 *     mu    = 1/L sum_l m_l                                  [mu]
 *     sigma = sqrt(1/(L-1) sum_l (m_l - mu)^2)               [sigma]
 * and, given a member per row (trajectory sampling), that member's m_l and raw log-variance x, or
 * its aleatoric std in the model's units (PETS soft bounds [lo, hi] on the log-variance, then
 * scale * exp(v / 2)):
 *     v     = lo + softplus(hi - softplus(hi - x) - lo)
 *     std   = scale * exp(lo / 2) * sqrt(1 + exp(hi - lo) / (1 + exp(hi - x)))
 * (the same function: exp(softplus(z)) = 1 + exp(z) twice), one exp per value instead of the
 * nine passes of the torch ops; exp(hi - x) overflowing to inf gives the limit v = lo exactly.
 *
 * A deterministic planning step can finish in the same pass: given the hallucinated control eta
 * (beta already applied), the mean output is SoftAE's optimistic next state
 *     s'    = mu + sigma * eta                               (else s' = mu)
 * and, given the next step's network input, its state columns receive s' as the network takes it,
 * (s' - in_loc) / in_scale. A trajectory-sampling step (PETS) finishes the same way: given standard
 * normal draws z and a member per row, the first output is that member's sampled next state
 *     s'    = m_l + std * z                                  (m_l without the log-variance head)
 * instead of mu. At a plan's first step a candidate's particles share its state and action: with
 * `share` = P, output row n reads row n / P of the network output and of the state, so the network
 * ran once for them. Right after a network call every torch op touches cache-cold code and
 * data (on the AMX Xeon a 4-element add took 6-26 us there against 2 us in a loop:
 * benchmarks/studies/cold_ops.py); these are the three ops and the concatenation a step would otherwise run
 * between two network calls.
 *
 * Why: done with torch ops this is about ten passes over (L, N, d_s) tensors (the bf16-to-fp32
 * copy, the member means, mean, centring, square, sum, the member gather), each a kernel launch;
 * at the 2060 rows of a 10-particle plan the (L, N, d_s) tensors leave the L2 cache. Here each
 * row is read once, where it lies in the network's output buffer (any member and row stride), and
 * only the (N, d_s) results are written. benchmarks/planning_speed.py --compare-moments (whole
 * plans) and --loop-overhead (one candidate evaluation) measure it against the torch ops.
 *
 * The arithmetic is the torch ops' in the same order (members summed in order, then scaled by
 * 1/L; squared deviations likewise), with separate multiplies and adds, so results agree with
 * them to rounding. AVX-512 (F, BW, VL), else AVX2 (eight dimensions per vector, no FMA, so the
 * same separate rounding), chosen at run time: elsewhere supported() is 0 and the ensemble runs the
 * torch ops (the compiler may still contract a multiply and an add of the AVX-512 variant). One
 * exception, for the same bits as the torch step: s' = mu + sigma * eta is one fused multiply-add
 * in both variants, as torch 2.13's vectorized addcmul computes it on AVX2 and AVX-512 CPUs
 * (written out, not left to the compiler). Built as the optional extension
 * torchrl_softae.modules._moments (pyproject.toml); OpenMP threads are torch's own (see silu.c).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>

enum { DTYPE_FLOAT32 = 0, DTYPE_BFLOAT16 = 1 };

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SOFTAE_X86 1
#include "vector_exp.h"
#endif

typedef struct {
    const char *y;            /* network output, element (l, n, j) at y + (l * sm + n * sn + j) * size */
    int64_t sm, sn;           /* member and row strides, in elements */
    int dtype;                /* DTYPE_FLOAT32 or DTYPE_BFLOAT16 */
    int64_t L, d;             /* members, state dimensions */
    int64_t logvar_offset;    /* column of the log-variance head (d), or -1 without it */
    int64_t share;            /* output rows per network-output and state row (a candidate's particles) */
    const float *state;       /* (N / share, d) contiguous, the model-space state s */
    const float *loc, *scale; /* (d,) output normalizer */
    const int64_t *member;    /* (N,) member per row, or NULL */
    float *mu, *sigma;        /* (N, d) outputs */
    float *picked, *picked_logvar; /* (N, d) outputs with member, or NULL (picked_logvar only with the head) */
    /* (d,) each, or NULL: picked_logvar receives the aleatoric std, std_scale = scale * exp(lo / 2),
     * span = exp(hi - lo) */
    const float *hi, *std_scale, *span;
    const float *eta;           /* (N, d) contiguous, or NULL: mu receives mu + sigma * eta */
    const float *noise;         /* (N, d) contiguous, or NULL; with member: mu receives m_l + std * z */
    float *next_input;          /* row n's state columns at next_input + n * next_stride, or NULL */
    int64_t next_stride;
    const float *in_loc, *in_scale; /* (d,) the input normalizer's state columns (with next_input) */
} moments_args;

/* members kept in registers (one __m512 each); the Python side reads it as MAX_MEMBERS */
#define MAX_VECTOR_MEMBERS 16

#ifdef SOFTAE_X86
/* ------------------------------------------------------------------ AVX-512
 * Sixteen state dimensions per vector (the last one masked), every member's mean kept in a
 * register between the sum and the squared deviations: each output element is read once. */

__attribute__((target("avx512f,avx512bw,avx512vl"))) static inline __m512 load_avx512(const moments_args *a, int64_t offset,
                                                                             __mmask16 m) {
    if (a->dtype == DTYPE_FLOAT32) return _mm512_maskz_loadu_ps(m, (const float *)a->y + offset);
    __m256i h = _mm256_maskz_loadu_epi16(m, (const uint16_t *)a->y + offset);
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(h), 16));
}

__attribute__((target("avx512f,avx512bw,avx512vl"))) static void moments_row_avx512(const moments_args *a, int64_t n) {
    const int64_t L = a->L, d = a->d, src = n / a->share, row = src * a->sn;
    const __m512 inv_l = _mm512_set1_ps(1.0f / (float)L), inv_dof = _mm512_set1_ps(1.0f / (float)(L > 1 ? L - 1 : 1));
    __m512 m[MAX_VECTOR_MEMBERS];
    for (int64_t j = 0; j < d; j += 16) {
        const __mmask16 k = d - j >= 16 ? (__mmask16)0xffff : (__mmask16)((1u << (d - j)) - 1u);
        const __m512 base = _mm512_add_ps(_mm512_maskz_loadu_ps(k, a->state + src * d + j), _mm512_maskz_loadu_ps(k, a->loc + j));
        const __m512 sc = _mm512_maskz_loadu_ps(k, a->scale + j);
        __m512 sum = _mm512_setzero_ps(), ss = _mm512_setzero_ps();
        for (int64_t l = 0; l < L; l++) {
            m[l] = _mm512_add_ps(base, _mm512_mul_ps(sc, load_avx512(a, l * a->sm + row + j, k)));
            sum = _mm512_add_ps(sum, m[l]);
        }
        const __m512 mean = _mm512_mul_ps(sum, inv_l);
        for (int64_t l = 0; l < L; l++) {
            const __m512 c = _mm512_sub_ps(m[l], mean);
            ss = _mm512_add_ps(ss, _mm512_mul_ps(c, c));
        }
        const __m512 sd = _mm512_sqrt_ps(_mm512_mul_ps(ss, inv_dof));
        __m512 next = mean;
        if (a->eta != NULL) next = _mm512_fmadd_ps(sd, _mm512_maskz_loadu_ps(k, a->eta + n * d + j), mean);
        if (a->member != NULL) {
            const int64_t l = a->member[n];
            if (a->picked != NULL) _mm512_mask_storeu_ps(a->picked + n * d + j, k, m[l]);
            __m512 x = _mm512_setzero_ps();
            if (a->logvar_offset >= 0) {
                x = load_avx512(a, l * a->sm + row + a->logvar_offset + j, k);
                if (a->hi != NULL) {
                    const __m512 one = _mm512_set1_ps(1.0f);
                    __m512 e = exp_avx512(_mm512_sub_ps(_mm512_maskz_loadu_ps(k, a->hi + j), x));
                    __m512 q = _mm512_div_ps(_mm512_maskz_loadu_ps(k, a->span + j), _mm512_add_ps(one, e));
                    x = _mm512_mul_ps(_mm512_maskz_loadu_ps(k, a->std_scale + j), _mm512_sqrt_ps(_mm512_add_ps(one, q)));
                }
                if (a->picked_logvar != NULL) _mm512_mask_storeu_ps(a->picked_logvar + n * d + j, k, x);
            }
            if (a->noise != NULL)
                next = a->logvar_offset >= 0
                           ? _mm512_add_ps(m[l], _mm512_mul_ps(x, _mm512_maskz_loadu_ps(k, a->noise + n * d + j)))
                           : m[l];
        }
        _mm512_mask_storeu_ps(a->mu + n * d + j, k, next);
        _mm512_mask_storeu_ps(a->sigma + n * d + j, k, sd);
        if (a->next_input != NULL)
            _mm512_mask_storeu_ps(a->next_input + n * a->next_stride + j, k,
                                  _mm512_div_ps(_mm512_sub_ps(next, _mm512_maskz_loadu_ps(k, a->in_loc + j)),
                                                _mm512_maskz_loadu_ps(k, a->in_scale + j)));
    }
}

/* ------------------------------------------------------------------ AVX2
 * The same with eight state dimensions per vector. AVX2 has no 16-bit masked load, so a tail
 * shorter than a vector goes through a zero-filled copy; AVX (and so AVX2) masks fp32 loads and
 * stores. Compiled without FMA: the multiplies and adds round separately, as the torch ops do. */

__attribute__((target("avx2"))) static inline __m256i tail_mask_avx2(int64_t count) {
    const __m256i lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    return _mm256_cmpgt_epi32(_mm256_set1_epi32((int)count), lanes);
}

__attribute__((target("avx2"))) static inline __m256 load_avx2(const moments_args *a, int64_t offset, int64_t count,
                                                               __m256i mask) {
    if (a->dtype == DTYPE_FLOAT32) return _mm256_maskload_ps((const float *)a->y + offset, mask);
    const uint16_t *src = (const uint16_t *)a->y + offset;
    __m128i h;
    if (count >= 8) {
        h = _mm_loadu_si128((const __m128i *)src);
    } else {
        uint16_t buf[8] = {0};
        for (int64_t i = 0; i < count; i++) buf[i] = src[i];
        h = _mm_loadu_si128((const __m128i *)buf);
    }
    return _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_cvtepu16_epi32(h), 16));
}

/* the aleatoric std from the raw log-variance x (see the top of this file); FMA for the exp */
__attribute__((target("avx2,fma"))) static __m256 aleatoric_std_avx2(const moments_args *a, int64_t j, __m256i k,
                                                                     __m256 x) {
    const __m256 one = _mm256_set1_ps(1.0f);
    __m256 e = exp_avx2(_mm256_sub_ps(_mm256_maskload_ps(a->hi + j, k), x));
    __m256 q = _mm256_div_ps(_mm256_maskload_ps(a->span + j, k), _mm256_add_ps(one, e));
    return _mm256_mul_ps(_mm256_maskload_ps(a->std_scale + j, k), _mm256_sqrt_ps(_mm256_add_ps(one, q)));
}

/* SoftAE's s' = mu + sigma * eta in one rounding, as torch's addcmul gives it on AVX2 CPUs (a
 * function of its own: the row's other multiplies and adds keep their separate roundings) */
__attribute__((target("avx2,fma"))) static __m256 optimistic_next_avx2(__m256 mean, __m256 sd, __m256 eta) {
    return _mm256_fmadd_ps(sd, eta, mean);
}

__attribute__((target("avx2"))) static void moments_row_avx2(const moments_args *a, int64_t n) {
    const int64_t L = a->L, d = a->d, src = n / a->share, row = src * a->sn;
    const __m256 inv_l = _mm256_set1_ps(1.0f / (float)L), inv_dof = _mm256_set1_ps(1.0f / (float)(L > 1 ? L - 1 : 1));
    __m256 m[MAX_VECTOR_MEMBERS];
    for (int64_t j = 0; j < d; j += 8) {
        const int64_t count = d - j >= 8 ? 8 : d - j;
        const __m256i k = tail_mask_avx2(count);
        const __m256 base = _mm256_add_ps(_mm256_maskload_ps(a->state + src * d + j, k), _mm256_maskload_ps(a->loc + j, k));
        const __m256 sc = _mm256_maskload_ps(a->scale + j, k);
        __m256 sum = _mm256_setzero_ps(), ss = _mm256_setzero_ps();
        for (int64_t l = 0; l < L; l++) {
            m[l] = _mm256_add_ps(base, _mm256_mul_ps(sc, load_avx2(a, l * a->sm + row + j, count, k)));
            sum = _mm256_add_ps(sum, m[l]);
        }
        const __m256 mean = _mm256_mul_ps(sum, inv_l);
        for (int64_t l = 0; l < L; l++) {
            const __m256 c = _mm256_sub_ps(m[l], mean);
            ss = _mm256_add_ps(ss, _mm256_mul_ps(c, c));
        }
        const __m256 sd = _mm256_sqrt_ps(_mm256_mul_ps(ss, inv_dof));
        __m256 next = mean;
        if (a->eta != NULL) next = optimistic_next_avx2(mean, sd, _mm256_maskload_ps(a->eta + n * d + j, k));
        if (a->member != NULL) {
            const int64_t l = a->member[n];
            if (a->picked != NULL) _mm256_maskstore_ps(a->picked + n * d + j, k, m[l]);
            __m256 x = _mm256_setzero_ps();
            if (a->logvar_offset >= 0) {
                x = load_avx2(a, l * a->sm + row + a->logvar_offset + j, count, k);
                if (a->hi != NULL) x = aleatoric_std_avx2(a, j, k, x);
                if (a->picked_logvar != NULL) _mm256_maskstore_ps(a->picked_logvar + n * d + j, k, x);
            }
            if (a->noise != NULL)
                next = a->logvar_offset >= 0
                           ? _mm256_add_ps(m[l], _mm256_mul_ps(x, _mm256_maskload_ps(a->noise + n * d + j, k)))
                           : m[l];
        }
        _mm256_maskstore_ps(a->mu + n * d + j, k, next);
        _mm256_maskstore_ps(a->sigma + n * d + j, k, sd);
        if (a->next_input != NULL) {
            /* masked lanes of in_scale load as 0: 0 / 0 there is never stored */
            const __m256 v = _mm256_div_ps(_mm256_sub_ps(next, _mm256_maskload_ps(a->in_loc + j, k)),
                                           _mm256_maskload_ps(a->in_scale + j, k));
            _mm256_maskstore_ps(a->next_input + n * a->next_stride + j, k, v);
        }
    }
}
#endif

/* ------------------------------------------------------------------ dispatch */
typedef void (*row_fn)(const moments_args *, int64_t);
typedef struct {
    const char *name;
    row_fn row;
    int supported;
} variant;

static variant VARIANTS[] = {
#ifdef SOFTAE_X86
    {"avx2", moments_row_avx2, 0},
    {"avx512", moments_row_avx512, 0},
#endif
    {NULL, NULL, 0},
};
#define N_VARIANTS ((int)(sizeof(VARIANTS) / sizeof(VARIANTS[0])) - 1)
static int CURRENT = -1; /* the variant in use; -1: this CPU runs none */

static void detect(void) { /* the best variant this CPU runs, in the order of VARIANTS */
#ifdef SOFTAE_X86
    __builtin_cpu_init();
    /* libgcc's feature bits include the OS check (XCR0) that the AVX state is enabled */
    VARIANTS[0].supported = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"); /* every AVX2 CPU so far */
    VARIANTS[1].supported = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw")
                            && __builtin_cpu_supports("avx512vl");
#endif
    for (int i = 0; i < N_VARIANTS; i++)
        if (VARIANTS[i].supported) CURRENT = i;
}

/* below this many elements one thread does it all (waking the other costs more) */
#define MIN_PARALLEL_ELEMENTS ((int64_t)32768)

static PyObject *ensemble_moments(PyObject *self, PyObject *args) {
    unsigned long long y, state, loc, scale, member, mu, sigma, picked, picked_logvar, hi, std_scale, span, eta,
        noise, next_input, in_loc, in_scale;
    long long sm, sn, L, N, d, logvar_offset, share, next_stride;
    int dtype, threads;
    (void)self;
    if (!PyArg_ParseTuple(args, "KLLiLLLLLKKKKKKKKKKKKKKLKKi", &y, &sm, &sn, &dtype, &L, &N, &d, &logvar_offset, &share,
                          &state, &loc, &scale, &member, &mu, &sigma, &picked, &picked_logvar, &hi, &std_scale, &span,
                          &eta, &noise, &next_input, &next_stride, &in_loc, &in_scale, &threads))
        return NULL;
    if (dtype != DTYPE_FLOAT32 && dtype != DTYPE_BFLOAT16) {
        PyErr_Format(PyExc_ValueError, "ensemble_moments: dtype code %d, expected 0 (float32) or 1 (bfloat16)", dtype);
        return NULL;
    }
    if (CURRENT < 0) {
        PyErr_SetString(PyExc_RuntimeError, "ensemble_moments: this CPU lacks AVX2");
        return NULL;
    }
    /* noise needs a member per row and, with the log-variance head, its aleatoric std (the bounds) */
    if (L < 1 || L > MAX_VECTOR_MEMBERS || N < 0 || d < 1 || share < 1 || N % share || !y || !state || !loc || !scale
        || !mu || !sigma || ((hi || std_scale || span) && !(hi && std_scale && span))
        || (noise && (!member || eta || (logvar_offset >= 0 && !hi)))
        || (next_input && (!in_loc || !in_scale || next_stride < d))) {
        PyErr_Format(PyExc_ValueError, "ensemble_moments: L=%lld (expected 1..%d), N=%lld, d=%lld, share=%lld (a "
                     "divisor of N), or a missing address", L, MAX_VECTOR_MEMBERS, N, d, share);
        return NULL;
    }
    moments_args a = {(const char *)(uintptr_t)y, sm, sn, dtype, L, d, logvar_offset, share,
                      (const float *)(uintptr_t)state, (const float *)(uintptr_t)loc, (const float *)(uintptr_t)scale,
                      (const int64_t *)(uintptr_t)member, (float *)(uintptr_t)mu, (float *)(uintptr_t)sigma,
                      (float *)(uintptr_t)picked, (float *)(uintptr_t)picked_logvar, (const float *)(uintptr_t)hi,
                      (const float *)(uintptr_t)std_scale, (const float *)(uintptr_t)span, (const float *)(uintptr_t)eta,
                      (const float *)(uintptr_t)noise, (float *)(uintptr_t)next_input, next_stride,
                      (const float *)(uintptr_t)in_loc, (const float *)(uintptr_t)in_scale};
    if (threads < 1) threads = 1;
    const int parallel = threads > 1 && N * L * d >= MIN_PARALLEL_ELEMENTS;
    const row_fn row = VARIANTS[CURRENT].row;
    Py_BEGIN_ALLOW_THREADS
#pragma omp parallel for num_threads(threads) schedule(static) if (parallel)
    for (int64_t n = 0; n < (int64_t)N; n++) row(&a, n);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *supported(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    return PyBool_FromLong(CURRENT >= 0);
}

#include "isa_variants.h"

static PyMethodDef METHODS[] = {
    {"supported", supported, METH_NOARGS, "whether this CPU runs the kernel (AVX2, or AVX-512 F, BW and VL)"},
    SOFTAE_ISA_METHODS,
    {"ensemble_moments", ensemble_moments, METH_VARARGS,
     "ensemble_moments(y, member_stride, row_stride, dtype, L, N, d, logvar_offset, share, state, loc, scale, "
     "member, mu, sigma, picked, picked_logvar, hi, std_scale, span, eta, noise, next_input, next_stride, in_loc, "
     "in_scale, threads): mu (or mu + sigma * eta, or a picked member's mean plus its aleatoric std times noise) "
     "and sigma (and a picked member's mean and raw log-variance, or with hi, std_scale and span its aleatoric "
     "std) of an ensemble's raw output, output row n from its row n / share, and the first output normalized into "
     "the next input's rows; addresses of contiguous float32 buffers, 0 for none"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_moments", "ensemble mean and epistemic std in one pass",
                                    -1, METHODS, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__moments(void) {
    detect();
    PyObject *module = PyModule_Create(&MODULE);
    if (module != NULL && PyModule_AddIntConstant(module, "MAX_MEMBERS", MAX_VECTOR_MEMBERS) < 0) Py_CLEAR(module);
    return module;
}
