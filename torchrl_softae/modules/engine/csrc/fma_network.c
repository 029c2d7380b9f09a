/* The ensemble's whole network in one call: every layer of every member by register blocks of fused
 * multiply-adds, each hidden layer's bias and SiLU applied to its block while it is still in
 * registers, the last layer written out in fp32. In fp32 on AVX-512 or AVX2 with FMA; in bf16
 * (weights and hidden activations, fp32 accumulation) on AVX512-BF16, whose VDPBF16PS adds a pair
 * of bf16 products per fp32 lane: a CPU with AVX512-BF16 but no AMX (AMD EPYC Zen 4) has no other
 * whole-network bf16 kernel (amx_network.c needs AMX). On the AMX Xeon the bf16 form is 1.4-1.6x
 * slower than the fp32 one (VDPBF16PS issues at about a third of the FMA rate there) and never
 * chosen; on the AMD EPYC with AVX512-BF16 the bf16 GEMM peak is 1.94x the fp32 one.
 *
 * Why: in fp32 a network call through torch is five oneDNN or MKL calls, each reading and writing
 * its layer's whole output, plus a SiLU pass per hidden layer. On the AMX Xeon the best of them ran
 * a 10-particle arm call (2060 rows per member) at 75-80 % of the fp32 GEMM peak and a one-particle
 * call (206 rows) at 61-64 %; this kernel, interleaved with them, at 84-90 % and 78-81 % (four
 * runs of benchmarks/studies/network_paths_speed.py). Prefetching the next member's weights into L2 during
 * a thread's last units of a member was tried and gained nothing (the hardware prefetchers keep up).
 * A work unit is one member's block of up to ROWS rows carried through all layers: its activations
 * (ROWS x 256, 12 KiB in fp32) stay in L1, the member's weights (about 1 MiB in fp32) stream from
 * L2, each weight vector loaded once per block of rows, and there is one OpenMP fork per call.
 *
 * Layout (the Python side packs it, torchrl_softae/modules/engine/fma_network.py):
 *   x      (N, d_in) fp32, row-major: the normalized input every member shares;
 *   weight fp32: (L, Mp / 32, K, 32) per layer, panel p holding W[k][32 p + j];
 *          bf16: (L, Mp / 32, K / 2, 32, 2) per layer, panel p holding W[2 i + t][32 p + j] at
 *          [i][j][t] (pairs of inputs next to each other, as VDPBF16PS reads them);
 *          zeros where 32 p + j is padding or k >= the layer's inputs; K: the layer's inputs as
 *          packed (fp32: the first layer's d_in, then the previous layer's Mp; bf16: even, the first
 *          layer's at least d_in), Mp: its outputs padded to a multiple of 32;
 *   bias   (L, Mp) fp32 per layer (zeros in the padding: padded columns stay silu(0) = 0);
 *   out    (L, N, C) fp32, the last layer's first C outputs plus its bias.
 *
 * Built at install time as the optional extension torchrl_softae.modules._fma_network
 * (pyproject.toml); the instruction set is chosen at run time (fp32: AVX-512F, else AVX2 with FMA;
 * bf16: AVX512-BF16; on a CPU without them that form is not offered). Like every inference path it
 * is a candidate the ensemble measures, never assumed faster (torchrl_softae/modules/engine/paths.py).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SOFTAE_X86 1
#include "silu_bf16grade.h"
#include "silu_fp32.h"
#endif

#define KERNEL_NAME "fma_network"
#include "whole_network.h"

#define PANEL 32    /* output columns per packed weight panel */
#define ROWS_512 12 /* rows per block, AVX-512: 12 x 32 accumulators = 24 of the 32 registers */
#define ROWS_256 6  /* rows per block, AVX2: 6 x 16 accumulators = 12 of the 16 registers */

/* where a block's results go: a hidden layer's SiLU into the next layer's input buffer (all 32
 * columns, row stride `stride` elements: fp32, or bf16 in the bf16 form), or the last layer's first
 * `cols` columns of the fp32 output from column `col0` (row stride `cols`) */
typedef struct {
    void *dst;
    int64_t stride, col0, cols;
    int hidden;
} epilogue;

#ifdef SOFTAE_X86
#define AVX512 __attribute__((target("avx512f,avx512bw,avx512vl,fma")))
#define AVX2 __attribute__((target("avx2,fma")))
#define INLINE inline __attribute__((always_inline))

/* block function NAME: one copy of PANEL (an always-inlined panel of `rows` rows) per row count
 * 1-12, so that in each `rows` is a constant and the accumulators live in registers (the AVX2
 * panel has at most 6 rows: its larger cases are never called) */
#define BLOCK_FUNCTION(TARGET, NAME, PANEL_FN, T)                                                          \
    TARGET static void NAME(int rows, const void *a_, int64_t lda, const void *w_, int64_t k, const float *bias, \
                            const epilogue *e) {                                                            \
        const T *a = a_, *w = w_;                                                                        \
        switch (rows) {                                                                                  \
        case 1: PANEL_FN(1, a, lda, w, k, bias, e); break;                                               \
        case 2: PANEL_FN(2, a, lda, w, k, bias, e); break;                                               \
        case 3: PANEL_FN(3, a, lda, w, k, bias, e); break;                                               \
        case 4: PANEL_FN(4, a, lda, w, k, bias, e); break;                                               \
        case 5: PANEL_FN(5, a, lda, w, k, bias, e); break;                                               \
        case 6: PANEL_FN(6, a, lda, w, k, bias, e); break;                                               \
        case 7: PANEL_FN(7, a, lda, w, k, bias, e); break;                                               \
        case 8: PANEL_FN(8, a, lda, w, k, bias, e); break;                                               \
        case 9: PANEL_FN(9, a, lda, w, k, bias, e); break;                                               \
        case 10: PANEL_FN(10, a, lda, w, k, bias, e); break;                                             \
        case 11: PANEL_FN(11, a, lda, w, k, bias, e); break;                                             \
        case 12: PANEL_FN(12, a, lda, w, k, bias, e); break;                                             \
        }                                                                                                \
    }

/* the last layer's epilogue: out[r][col0 + j] = c[r][j] + bias[j], for the output's columns only */
AVX512 static INLINE void store_output_512(__m512 c[][2], const int rows, __m512 b0, __m512 b1, const epilogue *e) {
    float *out = e->dst;
    const __mmask16 m0 = first16(e->cols - e->col0), m1 = first16(e->cols - e->col0 - 16);
#pragma GCC unroll 12
    for (int r = 0; r < rows; r++) {
        _mm512_mask_storeu_ps(out + r * e->cols + e->col0, m0, _mm512_add_ps(c[r][0], b0));
        _mm512_mask_storeu_ps(out + r * e->cols + e->col0 + 16, m1, _mm512_add_ps(c[r][1], b1));
    }
}

/* rows x 32 = a (rows x k, row stride lda) @ panel (k x 32), then + bias and the epilogue. `rows`
 * is a constant wherever this is inlined (block_512 below), so the accumulators live in registers */
AVX512 static INLINE void panel_512(const int rows, const float *a, int64_t lda, const float *w, int64_t k,
                                    const float *bias, const epilogue *e) {
    __m512 c[ROWS_512][2];
#pragma GCC unroll 12
    for (int r = 0; r < rows; r++) c[r][0] = c[r][1] = _mm512_setzero_ps();
    for (int64_t i = 0; i < k; i++) {
        const __m512 w0 = _mm512_loadu_ps(w + PANEL * i), w1 = _mm512_loadu_ps(w + PANEL * i + 16);
#pragma GCC unroll 12
        for (int r = 0; r < rows; r++) {
            const __m512 v = _mm512_set1_ps(a[r * lda + i]);
            c[r][0] = _mm512_fmadd_ps(v, w0, c[r][0]);
            c[r][1] = _mm512_fmadd_ps(v, w1, c[r][1]);
        }
    }
    const __m512 b0 = _mm512_loadu_ps(bias), b1 = _mm512_loadu_ps(bias + 16);
    if (e->hidden) {
        float *dst = e->dst;
#pragma GCC unroll 12
        for (int r = 0; r < rows; r++) {
            _mm512_storeu_ps(dst + r * e->stride, silu_avx512(_mm512_add_ps(c[r][0], b0)));
            _mm512_storeu_ps(dst + r * e->stride + 16, silu_avx512(_mm512_add_ps(c[r][1], b1)));
        }
    } else {
        store_output_512(c, rows, b0, b1, e);
    }
}

BLOCK_FUNCTION(AVX512, block_512, panel_512, float)

AVX2 static inline __m256i first8(int64_t k) {
    const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    return _mm256_cmpgt_epi32(_mm256_set1_epi32((int)(k < 0 ? 0 : k > 8 ? 8 : k)), lane);
}

/* the AVX2 form: the panel's 32 columns as two halves of 16 (two registers of 8 per row); the
 * packing is the same, a half's row i being 16 floats at w + 32 i + 16 h */
AVX2 static INLINE void panel_256(const int rows, const float *a, int64_t lda, const float *w, int64_t k,
                                  const float *bias, const epilogue *e) {
    if (rows > ROWS_256) __builtin_unreachable(); /* block_256 is only called with up to ROWS_256 rows */
    for (int h = 0; h < 2; h++) {
        __m256 c[ROWS_256][2];
#pragma GCC unroll 6
        for (int r = 0; r < rows; r++) c[r][0] = c[r][1] = _mm256_setzero_ps();
        const float *wh = w + 16 * h;
        for (int64_t i = 0; i < k; i++) {
            const __m256 w0 = _mm256_loadu_ps(wh + PANEL * i), w1 = _mm256_loadu_ps(wh + PANEL * i + 8);
#pragma GCC unroll 6
            for (int r = 0; r < rows; r++) {
                const __m256 v = _mm256_broadcast_ss(a + r * lda + i);
                c[r][0] = _mm256_fmadd_ps(v, w0, c[r][0]);
                c[r][1] = _mm256_fmadd_ps(v, w1, c[r][1]);
            }
        }
        const __m256 b0 = _mm256_loadu_ps(bias + 16 * h), b1 = _mm256_loadu_ps(bias + 16 * h + 8);
        float *dst = e->dst;
        if (e->hidden) {
#pragma GCC unroll 6
            for (int r = 0; r < rows; r++) {
                _mm256_storeu_ps(dst + r * e->stride + 16 * h, silu_avx2(_mm256_add_ps(c[r][0], b0)));
                _mm256_storeu_ps(dst + r * e->stride + 16 * h + 8, silu_avx2(_mm256_add_ps(c[r][1], b1)));
            }
        } else {
            const int64_t col = e->col0 + 16 * h;
            const __m256i m0 = first8(e->cols - col), m1 = first8(e->cols - col - 8);
#pragma GCC unroll 6
            for (int r = 0; r < rows; r++) {
                _mm256_maskstore_ps(dst + r * e->cols + col, m0, _mm256_add_ps(c[r][0], b0));
                _mm256_maskstore_ps(dst + r * e->cols + col + 8, m1, _mm256_add_ps(c[r][1], b1));
            }
        }
    }
}

BLOCK_FUNCTION(AVX2, block_256, panel_256, float)

/* ------------------------------------------------------------------ bf16: VDPBF16PS */
#define AVX512BF16 __attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16,fma")))

/* the bf16 form of panel_512: a (rows x kp bf16) @ panel (kp / 2 pairs x 32 columns x 2 bf16),
 * each VDPBF16PS adding a pair of inputs times a pair of weights to 16 fp32 accumulators; a
 * hidden layer's SiLU (bf16-grade, as the AMX kernel's) rounded to bf16 into the next input */
AVX512BF16 static INLINE void panel_bf16(const int rows, const uint16_t *a, int64_t lda, const uint16_t *w, int64_t kp,
                                        const float *bias, const epilogue *e) {
    __m512 c[ROWS_512][2];
#pragma GCC unroll 12
    for (int r = 0; r < rows; r++) c[r][0] = c[r][1] = _mm512_setzero_ps();
    for (int64_t i = 0; i < kp / 2; i++) {
        const __m512bh w0 = (__m512bh)_mm512_loadu_si512(w + 2 * PANEL * i);
        const __m512bh w1 = (__m512bh)_mm512_loadu_si512(w + 2 * PANEL * i + PANEL);
#pragma GCC unroll 12
        for (int r = 0; r < rows; r++) {
            int32_t pair;
            memcpy(&pair, a + r * lda + 2 * i, sizeof(pair));
            const __m512bh v = (__m512bh)_mm512_set1_epi32(pair);
            c[r][0] = _mm512_dpbf16_ps(c[r][0], v, w0);
            c[r][1] = _mm512_dpbf16_ps(c[r][1], v, w1);
        }
    }
    const __m512 b0 = _mm512_loadu_ps(bias), b1 = _mm512_loadu_ps(bias + 16);
    if (e->hidden) {
        uint16_t *dst = e->dst;
#pragma GCC unroll 12
        for (int r = 0; r < rows; r++) {
            const __m512 y0 = silu_bf16grade_avx512(_mm512_add_ps(c[r][0], b0));
            const __m512 y1 = silu_bf16grade_avx512(_mm512_add_ps(c[r][1], b1));
            _mm512_storeu_si512(dst + r * e->stride, (__m512i)_mm512_cvtne2ps_pbh(y1, y0));
        }
    } else {
        store_output_512(c, rows, b0, b1, e);
    }
}

BLOCK_FUNCTION(AVX512BF16, block_bf16, panel_bf16, uint16_t)

#endif

/* ------------------------------------------------------------------ dispatch */
typedef void (*block_fn)(int, const void *, int64_t, const void *, int64_t, const float *, const epilogue *);
typedef struct {
    const char *name;
    block_fn block;
    int rows;      /* rows per block */
    int elem;      /* bytes per weight and activation: 4 (fp32) or 2 (bf16) */
    int supported;
} variant;

/* the fp32 variants, worst to best (isa(), use_isa()) */
static variant VARIANTS[] = {
#ifdef SOFTAE_X86
    {"avx2", block_256, ROWS_256, 4, 0},
    {"avx512f", block_512, ROWS_512, 4, 0},
#else
    {"none", NULL, 1, 4, 0},
#endif
};
#define N_VARIANTS ((int)(sizeof(VARIANTS) / sizeof(VARIANTS[0])))
static int CURRENT = -1;

/* the bf16 form (weights and hidden activations in bf16, fp32 accumulation) */
#ifdef SOFTAE_X86
static variant BF16 = {"avx512bf16", block_bf16, ROWS_512, 2, 0};
#else
static variant BF16 = {"none", NULL, 1, 2, 0};
#endif

static void detect(void) { /* the best variant this CPU runs, in the order of VARIANTS */
#ifdef SOFTAE_X86
    __builtin_cpu_init();
    /* libgcc's feature bits include the OS check (XCR0) that the AVX-512 state is enabled */
    VARIANTS[0].supported = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    VARIANTS[1].supported = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                            __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("fma");
    BF16.supported = VARIANTS[1].supported && __builtin_cpu_supports("avx512bf16");
#endif
    for (int i = 0; i < N_VARIANTS; i++)
        if (VARIANTS[i].supported) CURRENT = i;
}

/* rows [row0, row0 + rows) of one member through every layer; a, b: two buffers of the variant's
 * rows x (widest layer) elements. fp32 reads the first layer's input from x itself; bf16 first
 * rounds it into a (the packed inputs of the first layer, zero-padded to an even count). */
static void run_unit(const network *net, const variant *v, int64_t member, int64_t row0, int rows, char *a, char *b,
                     int64_t width) {
    const int elem = v->elem;
    const void *in = net->x + row0 * net->d_in;
    int64_t lda = net->d_in;
    if (elem == 2) {
#ifdef SOFTAE_X86
        rows_to_bf16(net->x + row0 * net->d_in, net->d_in, rows, (uint16_t *)a, width, net->in[0]);
#endif
        in = a;
        lda = width;
    }
    for (int i = 0; i < net->layers; i++) {
        const int64_t k = net->in[i], mp = net->padded_out[i];
        const char *w = (const char *)net->weight[i] + member * mp * k * elem;
        const float *bias = net->bias[i] + member * mp;
        const int last = i == net->layers - 1;
        epilogue e = {last ? (void *)(net->out + (member * net->n + row0) * net->out_cols) : b, width, 0, net->out_cols,
                      !last};
        for (int64_t col0 = 0; col0 < mp; col0 += PANEL) {
            if (last && col0 >= net->out_cols) break;
            e.col0 = col0;
            if (!last) e.dst = b + col0 * elem;
            v->block(rows, in, lda, w + col0 * k * elem, k, bias + col0, &e);
        }
        in = b;
        lda = width;
        char *t = a;
        a = b;
        b = t;
    }
}

/* what a thread's range of units needs besides the range */
typedef struct {
    const network *net;
    const variant *v;
    int64_t blocks, width;
} units_job;

/* 0 on success, -1 where this thread's scratch could not be allocated (its units not computed).
 * A member's rows are split into `blocks` blocks of nearly equal size (at most the variant's rows
 * each): 206 rows run as 8 blocks of 12 and 10 of 11, not 17 of 12 and one of 2. */
static int run_units(const void *context, int64_t first_unit, int64_t last_unit) {
    const units_job *job = context;
    const network *net = job->net;
    const int64_t blocks = job->blocks, width = job->width, rows = job->v->rows, bytes = rows * width * job->v->elem;
    char *a = aligned_alloc(64, (size_t)(2 * bytes));
    if (a == NULL) return -1;
    for (int64_t u = first_unit; u < last_unit; u++) {
        const int64_t member = u / blocks, block = u % blocks;
        const int64_t row0 = net->n * block / blocks, row1 = net->n * (block + 1) / blocks;
        run_unit(net, job->v, member, row0, (int)(row1 - row0), a, a + bytes, width);
    }
    free(a);
    return 0;
}

/* 0 on success, -1 where a thread could not allocate its scratch (the output is then incomplete) */
static int run_network(const network *net, const variant *v, int threads) {
    units_job job = {net, v, (net->n + v->rows - 1) / v->rows, widest_layer(net)};
    return run_parallel(net->members * job.blocks, threads, run_units, &job);
}

static int forward_fp32(const network *net, int threads) { return run_network(net, &VARIANTS[CURRENT], threads); }

static int forward_bf16(const network *net, int threads) { return run_network(net, &BF16, threads); }

static PyObject *py_forward(PyObject *self, PyObject *args) {
    network net;
    int threads;
    (void)self;
    if (parse_network(args, 1, 1, &net, &threads) < 0) return NULL;
    if (CURRENT < 0) {
        PyErr_SetString(PyExc_RuntimeError, "fma_network.forward: not available here (the CPU has neither AVX-512F "
                                            "nor AVX2 with FMA)");
        return NULL;
    }
    return call_forward(&net, threads, forward_fp32);
}

static PyObject *py_forward_bf16(PyObject *self, PyObject *args) {
    network net;
    int threads;
    (void)self;
    if (parse_network(args, 2, 0, &net, &threads) < 0) return NULL;
    if (!BF16.supported) {
        PyErr_SetString(PyExc_RuntimeError, "fma_network.forward_bf16: not available here (the CPU has no "
                                            "AVX512-BF16)");
        return NULL;
    }
    return call_forward(&net, threads, forward_bf16);
}

static PyObject *py_bf16_supported(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    return PyBool_FromLong(BF16.supported);
}

#include "isa_variants.h"

static PyMethodDef METHODS[] = {
    {"forward", py_forward, METH_VARARGS,
     "forward(x, n, d_in, out, out_cols, members, weights, biases, in_features, padded_out, threads): the whole "
     "fp32 network on n shared rows (addresses of contiguous buffers in the layout of fma_network.c)"},
    {"forward_bf16", py_forward_bf16, METH_VARARGS,
     "forward_bf16(...): the same arguments, the network in its bf16 layout (fma_network.c)"},
    {"bf16_supported", py_bf16_supported, METH_NOARGS, "whether this CPU runs forward_bf16 (AVX512-BF16)"},
    SOFTAE_ISA_METHODS,
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_fma_network",
                                    "the ensemble's network by fp32 FMA register blocks", -1, METHODS, NULL, NULL, NULL,
                                    NULL};

/* part of the key of inference-path choices cached on disk (torchrl_softae/modules/engine/paths.py) */
#define SOFTAE_FMA_NETWORK_REVISION 2 /* 2: the bf16 form */

PyMODINIT_FUNC PyInit__fma_network(void) {
    detect();
    PyObject *module = PyModule_Create(&MODULE);
    if (module != NULL && PyModule_AddIntConstant(module, "REVISION", SOFTAE_FMA_NETWORK_REVISION) < 0)
        Py_CLEAR(module);
    return module;
}
