/* The ensemble's whole network in one call on a CPU with AMX: every layer of every member in bf16
 * tiles (TDPBF16PS, fp32 accumulation), each hidden layer's bias and SiLU applied to its tiles
 * while they are still in L1, the last layer written in fp32.
 *
 * Why: on the AMX Xeon a bf16 network call at 206 rows per member (one-particle planning) took
 * 870-920 us in five oneDNN or MKL calls plus a SiLU pass per hidden layer, a fifth of the bf16
 * GEMM peak: each call reads and writes its layer's whole output, and the small first (70 inputs)
 * and last (116 outputs) layers run far from the peak. Here a work unit is one member's block of
 * 32 rows (two 16-row tiles) carried through all layers: its activations (32 x 256 bf16, 16 KiB)
 * never leave L1, the member's weights (0.5 MiB in bf16) stay in L2, and there is one OpenMP
 * fork per network call instead of one per layer.
 *
 * Layout (the Python side packs it, torchrl_softae/modules/engine/amx_network.py):
 *   x      (N, d_in) fp32, row-major: the normalized input every member shares;
 *   weight (L, Mp / 16, Kp / 32, 16, 32) bf16 per layer: for output block nb and input block kb,
 *          one 16 x 32 tile in AMX's pair-interleaved (VNNI) form, element [r][2 j + t] being
 *          W[32 kb + 2 r + t][16 nb + j]; Kp, Mp: in and out features padded with zeros to
 *          multiples of 32 (a layer's Kp is the previous layer's Mp);
 *   bias   (L, Mp) fp32 per layer (zeros in the padding: padded columns stay silu(0) = 0);
 *   out    (L, N, C) fp32, the last layer's first C outputs plus its bias.
 *
 * Built at install time as the optional extension torchrl_softae.modules._amx_network
 * (pyproject.toml); it runs only where the CPU has AMX-TILE, AMX-BF16 and AVX512-BF16 and Linux
 * grants the tile state (arch_prctl), else available() is False and the ensemble never offers the
 * path. Like every inference path it is a candidate the ensemble measures, never assumed faster.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__x86_64__) && defined(__GNUC__) && defined(__linux__)
#include <cpuid.h>
#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>
#define SOFTAE_AMX 1
#include "silu_bf16grade.h"
#endif

#define KERNEL_NAME "amx_network"
#include "whole_network.h"

#define UNIT_ROWS 32  /* rows of one work unit: two 16-row tiles */
#define TILE_ELEMS 512 /* bf16 values in one 16 x 32 weight tile */

static int AVAILABLE = 0;      /* the CPU has the instructions and Linux granted the tile state */
static const char *WHY_NOT = "not an x86-64 Linux build";

#ifdef SOFTAE_AMX
#define AMX __attribute__((target("amx-tile,amx-bf16,avx512f,avx512bw,avx512vl,avx512bf16")))
#define AVX512 __attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16")))

typedef struct __attribute__((aligned(64))) {
    uint8_t palette, start_row, reserved[14];
    uint16_t colsb[16];
    uint8_t rows[16];
} tile_config;

/* tiles 0-3: fp32 accumulators of a 32 x 32 output block (2 x 2 tiles of 16 x 16); 4-5: two
 * 16-row input tiles; 6-7: two weight tiles (32 inputs x 16 outputs each). All 16 x 64 bytes. */
AMX static void configure_tiles(void) {
    tile_config cfg;
    memset(&cfg, 0, sizeof(cfg));
    cfg.palette = 1;
    for (int t = 0; t < 8; t++) {
        cfg.rows[t] = 16;
        cfg.colsb[t] = 64;
    }
    _tile_loadconfig(&cfg);
}

/* c (32 x 32 fp32, row stride 32) = a (rows x kp bf16) @ the two weight column blocks w0, w1
 * (kb_count tiles each); `two`: both 16-row tiles of a, else the first only */
AMX static void block(const uint16_t *a, int64_t kp, const uint16_t *w0, const uint16_t *w1, int64_t kb_count,
                      int two, float *c) {
    const int64_t stride = kp * 2; /* bytes per row of a */
    _tile_zero(0);
    _tile_zero(1);
    if (two) {
        _tile_zero(2);
        _tile_zero(3);
        for (int64_t kb = 0; kb < kb_count; kb++) {
            _tile_loadd(4, a + kb * 32, stride);
            _tile_loadd(5, a + 16 * kp + kb * 32, stride);
            _tile_loadd(6, w0 + kb * TILE_ELEMS, 64);
            _tile_loadd(7, w1 + kb * TILE_ELEMS, 64);
            _tile_dpbf16ps(0, 4, 6);
            _tile_dpbf16ps(1, 4, 7);
            _tile_dpbf16ps(2, 5, 6);
            _tile_dpbf16ps(3, 5, 7);
        }
        _tile_stored(2, c + 16 * 32, 128);
        _tile_stored(3, c + 16 * 32 + 16, 128);
    } else {
        for (int64_t kb = 0; kb < kb_count; kb++) {
            _tile_loadd(4, a + kb * 32, stride);
            _tile_loadd(6, w0 + kb * TILE_ELEMS, 64);
            _tile_loadd(7, w1 + kb * TILE_ELEMS, 64);
            _tile_dpbf16ps(0, 4, 6);
            _tile_dpbf16ps(1, 4, 7);
        }
    }
    _tile_stored(0, c, 128);
    _tile_stored(1, c + 16, 128);
}

/* a hidden layer's epilogue: dst[r][0:32] = bf16(silu(c[r] + bias)) for r < rows */
AVX512 static void epilogue_silu(const float *c, const float *bias, uint16_t *dst, int64_t dst_stride, int rows) {
    const __m512 b0 = _mm512_loadu_ps(bias), b1 = _mm512_loadu_ps(bias + 16);
    for (int r = 0; r < rows; r++) {
        __m512 y0 = silu_bf16grade_avx512(_mm512_add_ps(_mm512_loadu_ps(c + 32 * r), b0));
        __m512 y1 = silu_bf16grade_avx512(_mm512_add_ps(_mm512_loadu_ps(c + 32 * r + 16), b1));
        _mm512_storeu_si512(dst + r * dst_stride, (__m512i)_mm512_cvtne2ps_pbh(y1, y0));
    }
}

/* the last layer's epilogue: out[r][col0 + j] = c[r][j] + bias[j] for r < rows, col0 + j < cols */
AVX512 static void epilogue_out(const float *c, const float *bias, float *out, int64_t cols, int64_t col0, int rows) {
    const __mmask16 m0 = first16(cols - col0), m1 = first16(cols - col0 - 16);
    const __m512 b0 = _mm512_loadu_ps(bias), b1 = _mm512_loadu_ps(bias + 16);
    for (int r = 0; r < rows; r++) {
        _mm512_mask_storeu_ps(out + r * cols + col0, m0, _mm512_add_ps(_mm512_loadu_ps(c + 32 * r), b0));
        _mm512_mask_storeu_ps(out + r * cols + col0 + 16, m1, _mm512_add_ps(_mm512_loadu_ps(c + 32 * r + 16), b1));
    }
}

/* a (UNIT_ROWS x kp bf16) = x's rows [row0, row0 + rows), zero-padded in columns and rows */
AVX512 static void load_input(const float *x, int64_t d_in, int64_t row0, int rows, uint16_t *a, int64_t kp) {
    rows_to_bf16(x + row0 * d_in, d_in, rows, a, kp, kp);
    memset(a + rows * kp, 0, (size_t)((UNIT_ROWS - rows) * kp) * 2);
}

/* one member's block of rows through every layer; a, b: two UNIT_ROWS x (widest layer) buffers */
AMX static void run_unit(const network *net, int64_t member, int64_t row0, uint16_t *a, uint16_t *b, float *c) {
    const int rows = (int)(net->n - row0 < UNIT_ROWS ? net->n - row0 : UNIT_ROWS);
    const int two = rows > 16;
    load_input(net->x, net->d_in, row0, rows, a, net->in[0]);
    for (int i = 0; i < net->layers; i++) {
        const int64_t kp = net->in[i], mp = net->padded_out[i], kb_count = kp / 32;
        const uint16_t *w = (const uint16_t *)net->weight[i] + member * mp * kp;
        const float *bias = net->bias[i] + member * mp;
        const int last = i == net->layers - 1;
        for (int64_t col0 = 0; col0 < mp; col0 += 32) {
            if (last && col0 >= net->out_cols) break;
            const uint16_t *w0 = w + (col0 / 16) * kb_count * TILE_ELEMS;
            block(a, kp, w0, w0 + kb_count * TILE_ELEMS, kb_count, two, c);
            if (last)
                epilogue_out(c, bias + col0, net->out + (member * net->n + row0) * net->out_cols, net->out_cols, col0,
                             rows);
            else
                epilogue_silu(c, bias + col0, b + col0, mp, two ? UNIT_ROWS : 16);
        }
        uint16_t *t = a;
        a = b;
        b = t;
    }
}

/* what a thread's range of units needs besides the range */
typedef struct {
    const network *net;
    int64_t blocks, width;
} units_job;

/* 0 on success, -1 where this thread's scratch could not be allocated (its units not computed) */
AMX static int run_units(const void *context, int64_t first_unit, int64_t last_unit) {
    const units_job *job = context;
    uint16_t *a = aligned_alloc(64, (size_t)(2 * UNIT_ROWS * job->width * 2));
    float *c = aligned_alloc(64, UNIT_ROWS * 32 * sizeof(float));
    if (a == NULL || c == NULL) {
        free(a);
        free(c);
        return -1;
    }
    configure_tiles();
    for (int64_t u = first_unit; u < last_unit; u++)
        run_unit(job->net, u / job->blocks, (u % job->blocks) * UNIT_ROWS, a, a + UNIT_ROWS * job->width, c);
    _tile_release();
    free(a);
    free(c);
    return 0;
}

/* 0 on success, -1 where a thread could not allocate its scratch (the output is then incomplete) */
static int forward(const network *net, int threads) {
    units_job job = {net, (net->n + UNIT_ROWS - 1) / UNIT_ROWS, widest_layer(net)};
    return run_parallel(net->members * job.blocks, threads, run_units, &job);
}

static void detect(void) {
    unsigned eax, ebx, ecx, edx;
    if (!__get_cpuid_count(7, 0, &eax, &ebx, &ecx, &edx) || !(edx & (1u << 24)) || !(edx & (1u << 22))) {
        WHY_NOT = "the CPU has no AMX-TILE / AMX-BF16";
        return;
    }
    __builtin_cpu_init();
    if (!__builtin_cpu_supports("avx512bf16") || !__builtin_cpu_supports("avx512bw") ||
        !__builtin_cpu_supports("avx512vl")) {
        WHY_NOT = "the CPU has AMX but not AVX512-BF16/BW/VL";
        return;
    }
    /* Linux hands out the tile data state per process on request (ARCH_REQ_XCOMP_PERM for
     * XFEATURE_XTILEDATA); torch's oneDNN asks for it too, asking twice is harmless */
    if (syscall(SYS_arch_prctl, 0x1023, 18) != 0) {
        WHY_NOT = "Linux did not grant the AMX tile state (arch_prctl ARCH_REQ_XCOMP_PERM)";
        return;
    }
    AVAILABLE = 1;
    WHY_NOT = NULL;
}
#else
static int forward(const network *net, int threads) {
    (void)net;
    (void)threads;
    return -1;
}
static void detect(void) {}
#endif

static PyObject *py_forward(PyObject *self, PyObject *args) {
    network net;
    int threads;
    (void)self;
    if (parse_network(args, 32, 0, &net, &threads) < 0) return NULL;
    if (!AVAILABLE) {
        PyErr_Format(PyExc_RuntimeError, "amx_network.forward: not available here (%s)", WHY_NOT);
        return NULL;
    }
    return call_forward(&net, threads, forward);
}

static PyObject *py_available(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    return PyBool_FromLong(AVAILABLE);
}

static PyObject *py_why_not(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    if (WHY_NOT == NULL) Py_RETURN_NONE;
    return PyUnicode_FromString(WHY_NOT);
}

static PyMethodDef METHODS[] = {
    {"forward", py_forward, METH_VARARGS,
     "forward(x, n, d_in, out, out_cols, members, weights, biases, padded_in, padded_out, threads): the whole "
     "network on n shared rows (addresses of contiguous buffers in the layout of amx_network.c)"},
    {"available", py_available, METH_NOARGS, "whether this CPU and OS run the kernel"},
    {"why_not", py_why_not, METH_NOARGS, "why the kernel does not run here (None where it does)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_amx_network", "the ensemble's network in AMX tiles (bf16)",
                                    -1, METHODS, NULL, NULL, NULL, NULL};

/* part of the key of inference-path choices cached on disk (torchrl_softae/modules/engine/paths.py) */
#define SOFTAE_AMX_NETWORK_REVISION 1

PyMODINIT_FUNC PyInit__amx_network(void) {
    detect();
    PyObject *module = PyModule_Create(&MODULE);
    if (module != NULL && PyModule_AddIntConstant(module, "REVISION", SOFTAE_AMX_NETWORK_REVISION) < 0)
        Py_CLEAR(module);
    return module;
}
