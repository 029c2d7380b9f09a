/* The ensemble's whole network in one call, fp32: every layer of every member by FMA register
 * blocks (AVX-512, or AVX2 with FMA), each hidden layer's bias and SiLU applied to its block while
 * it is still in registers, the last layer written out.
 *
 * Why: in fp32 a network call through torch is five oneDNN or MKL calls, each reading and writing
 * its layer's whole output, plus a SiLU pass per hidden layer. On the AMX Xeon the best of them ran
 * a 10-particle arm call (2060 rows per member) at 76-80 % of the fp32 GEMM peak and a one-particle
 * call (206 rows) at 62-64 %; this kernel, interleaved with them, at 84-90 % and 78-81 % (three
 * runs of benchmarks/network_paths_speed.py). Prefetching the next member's weights into L2 during
 * a thread's last units of a member was tried and gained nothing (the hardware prefetchers keep up).
 * A work unit is one member's block of up to ROWS rows carried through all layers: its activations
 * (ROWS x 256 fp32, 12 KiB) stay in L1, the member's weights (about 1 MiB) stream from L2, each
 * weight vector loaded once per block of rows, and there is one OpenMP fork per network call.
 *
 * Layout (the Python side packs it, torchrl_softae/modules/fma_network.py):
 *   x      (N, d_in) fp32, row-major: the normalized input every member shares;
 *   weight (L, Mp / 32, K, 32) fp32 per layer: panel p holds W[k][32 p + j], zeros where
 *          32 p + j is padding; K: the layer's inputs (the previous layer's Mp), Mp: its outputs
 *          padded to a multiple of 32;
 *   bias   (L, Mp) fp32 per layer (zeros in the padding: padded columns stay silu(0) = 0);
 *   out    (L, N, C) fp32, the last layer's first C outputs plus its bias.
 *
 * Built at install time as the optional extension torchrl_softae.modules._fma_network
 * (pyproject.toml); the instruction set is chosen at run time (AVX-512F, else AVX2 with FMA; on a
 * CPU with neither the kernel is not offered). Like every inference path it is a candidate the
 * ensemble measures, never assumed faster (torchrl_softae/modules/paths.py).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SOFTAE_X86 1
#include "silu_fp32.h"
#endif

#define KERNEL_NAME "fma_network"
#include "whole_network.h"

#define PANEL 32    /* output columns per packed weight panel */
#define ROWS_512 12 /* rows per block, AVX-512: 12 x 32 accumulators = 24 of the 32 registers */
#define ROWS_256 6  /* rows per block, AVX2: 6 x 16 accumulators = 12 of the 16 registers */

/* where a block's results go: a hidden layer's SiLU into the next layer's input buffer (all 32
 * columns, row stride `stride`), or the last layer's first `cols` columns of the output from
 * column `col0` (row stride `cols`) */
typedef struct {
    float *dst;
    int64_t stride, col0, cols;
    int hidden;
} epilogue;

#ifdef SOFTAE_X86
#define AVX512 __attribute__((target("avx512f,avx512bw,avx512vl,fma")))
#define AVX2 __attribute__((target("avx2,fma")))
#define INLINE inline __attribute__((always_inline))

AVX512 static inline __mmask16 first16(int64_t k) { return k <= 0 ? 0 : k >= 16 ? 0xffff : (__mmask16)((1u << k) - 1u); }

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
#pragma GCC unroll 12
        for (int r = 0; r < rows; r++) {
            _mm512_storeu_ps(e->dst + r * e->stride, silu_avx512(_mm512_add_ps(c[r][0], b0)));
            _mm512_storeu_ps(e->dst + r * e->stride + 16, silu_avx512(_mm512_add_ps(c[r][1], b1)));
        }
    } else {
        const __mmask16 m0 = first16(e->cols - e->col0), m1 = first16(e->cols - e->col0 - 16);
#pragma GCC unroll 12
        for (int r = 0; r < rows; r++) {
            _mm512_mask_storeu_ps(e->dst + r * e->cols + e->col0, m0, _mm512_add_ps(c[r][0], b0));
            _mm512_mask_storeu_ps(e->dst + r * e->cols + e->col0 + 16, m1, _mm512_add_ps(c[r][1], b1));
        }
    }
}

/* one specialized copy of panel_512 per row count of a block */
AVX512 static void block_512(int rows, const float *a, int64_t lda, const float *w, int64_t k, const float *bias,
                             const epilogue *e) {
    switch (rows) {
#define ROWS_CASE(R) \
    case R: panel_512(R, a, lda, w, k, bias, e); break;
        ROWS_CASE(1) ROWS_CASE(2) ROWS_CASE(3) ROWS_CASE(4) ROWS_CASE(5) ROWS_CASE(6)
        ROWS_CASE(7) ROWS_CASE(8) ROWS_CASE(9) ROWS_CASE(10) ROWS_CASE(11) ROWS_CASE(12)
#undef ROWS_CASE
    }
}

AVX2 static inline __m256i first8(int64_t k) {
    const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    return _mm256_cmpgt_epi32(_mm256_set1_epi32((int)(k < 0 ? 0 : k > 8 ? 8 : k)), lane);
}

/* the AVX2 form: the panel's 32 columns as two halves of 16 (two registers of 8 per row); the
 * packing is the same, a half's row i being 16 floats at w + 32 i + 16 h */
AVX2 static INLINE void panel_256(const int rows, const float *a, int64_t lda, const float *w, int64_t k,
                                  const float *bias, const epilogue *e) {
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
        if (e->hidden) {
#pragma GCC unroll 6
            for (int r = 0; r < rows; r++) {
                _mm256_storeu_ps(e->dst + r * e->stride + 16 * h, silu_avx2(_mm256_add_ps(c[r][0], b0)));
                _mm256_storeu_ps(e->dst + r * e->stride + 16 * h + 8, silu_avx2(_mm256_add_ps(c[r][1], b1)));
            }
        } else {
            const int64_t col = e->col0 + 16 * h;
            const __m256i m0 = first8(e->cols - col), m1 = first8(e->cols - col - 8);
#pragma GCC unroll 6
            for (int r = 0; r < rows; r++) {
                _mm256_maskstore_ps(e->dst + r * e->cols + col, m0, _mm256_add_ps(c[r][0], b0));
                _mm256_maskstore_ps(e->dst + r * e->cols + col + 8, m1, _mm256_add_ps(c[r][1], b1));
            }
        }
    }
}

AVX2 static void block_256(int rows, const float *a, int64_t lda, const float *w, int64_t k, const float *bias,
                           const epilogue *e) {
    switch (rows) {
#define ROWS_CASE(R) \
    case R: panel_256(R, a, lda, w, k, bias, e); break;
        ROWS_CASE(1) ROWS_CASE(2) ROWS_CASE(3) ROWS_CASE(4) ROWS_CASE(5) ROWS_CASE(6)
#undef ROWS_CASE
    }
}
#endif

/* ------------------------------------------------------------------ dispatch */
typedef void (*block_fn)(int, const float *, int64_t, const float *, int64_t, const float *, const epilogue *);
typedef struct {
    const char *name;
    block_fn block;
    int rows, supported;
} variant;

static variant VARIANTS[] = {
#ifdef SOFTAE_X86
    {"avx2", block_256, ROWS_256, 0},
    {"avx512f", block_512, ROWS_512, 0},
#else
    {"none", NULL, 1, 0},
#endif
};
#define N_VARIANTS ((int)(sizeof(VARIANTS) / sizeof(VARIANTS[0])))
static int CURRENT = -1;

static void detect(void) { /* the best variant this CPU runs, in the order of VARIANTS */
#ifdef SOFTAE_X86
    __builtin_cpu_init();
    /* libgcc's feature bits include the OS check (XCR0) that the AVX-512 state is enabled */
    VARIANTS[0].supported = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    VARIANTS[1].supported = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                            __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("fma");
#endif
    for (int i = 0; i < N_VARIANTS; i++)
        if (VARIANTS[i].supported) CURRENT = i;
}

/* rows [row0, row0 + rows) of one member through every layer; a, b: two buffers of the variant's
 * rows x (widest layer) */
static void run_unit(const network *net, const variant *v, int64_t member, int64_t row0, int rows, float *a, float *b,
                     int64_t width) {
    const float *in = net->x + row0 * net->d_in;
    int64_t lda = net->d_in;
    for (int i = 0; i < net->layers; i++) {
        const int64_t k = net->in[i], mp = net->padded_out[i];
        const float *w = (const float *)net->weight[i] + member * mp * k, *bias = net->bias[i] + member * mp;
        const int last = i == net->layers - 1;
        epilogue e = {last ? net->out + (member * net->n + row0) * net->out_cols : b, width, 0, net->out_cols, !last};
        for (int64_t col0 = 0; col0 < mp; col0 += PANEL) {
            if (last && col0 >= net->out_cols) break;
            e.col0 = col0;
            if (!last) e.dst = b + col0;
            v->block(rows, in, lda, w + col0 * k, k, bias + col0, &e);
        }
        in = b;
        lda = width;
        float *t = a;
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
    const int64_t blocks = job->blocks, width = job->width, rows = job->v->rows;
    float *a = aligned_alloc(64, (size_t)(2 * rows * width) * sizeof(float));
    if (a == NULL) return -1;
    for (int64_t u = first_unit; u < last_unit; u++) {
        const int64_t member = u / blocks, block = u % blocks;
        const int64_t row0 = net->n * block / blocks, row1 = net->n * (block + 1) / blocks;
        run_unit(net, job->v, member, row0, (int)(row1 - row0), a, a + rows * width, width);
    }
    free(a);
    return 0;
}

/* 0 on success, -1 where a thread could not allocate its scratch (the output is then incomplete) */
static int forward(const network *net, int threads) {
    units_job job = {net, &VARIANTS[CURRENT], 0, 0};
    for (int i = 0; i < net->layers; i++)
        if (net->padded_out[i] > job.width) job.width = net->padded_out[i];
    job.blocks = (net->n + job.v->rows - 1) / job.v->rows;
    return run_parallel(net->members * job.blocks, threads, run_units, &job);
}

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
    return call_forward(&net, threads, forward);
}

#include "isa_variants.h"

static PyMethodDef METHODS[] = {
    {"forward", py_forward, METH_VARARGS,
     "forward(x, n, d_in, out, out_cols, members, weights, biases, in_features, padded_out, threads): the whole "
     "network on n shared rows (addresses of contiguous buffers in the layout of fma_network.c)"},
    SOFTAE_ISA_METHODS,
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_fma_network",
                                    "the ensemble's network by fp32 FMA register blocks", -1, METHODS, NULL, NULL, NULL,
                                    NULL};

/* part of the key of inference-path choices cached on disk (torchrl_softae/modules/paths.py) */
#define SOFTAE_FMA_NETWORK_REVISION 1

PyMODINIT_FUNC PyInit__fma_network(void) {
    detect();
    PyObject *module = PyModule_Create(&MODULE);
    if (module != NULL && PyModule_AddIntConstant(module, "REVISION", SOFTAE_FMA_NETWORK_REVISION) < 0)
        Py_CLEAR(module);
    return module;
}
