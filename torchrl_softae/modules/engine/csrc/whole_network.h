/* What the whole-network kernels share (amx_network.c: bf16 in AMX tiles; fma_network.c: fp32 in
 * FMA register blocks): the network as their forward() receives it from Python, checked once in
 * one place, and the split of work units (one member's block of rows each) between OpenMP threads.
 *
 * The including file defines KERNEL_NAME (a string, for error messages) before the #include. */
#ifndef SOFTAE_WHOLE_NETWORK_H
#define SOFTAE_WHOLE_NETWORK_H

#include <Python.h>
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define MAX_LAYERS 16

typedef struct {
    int layers;
    int64_t n, d_in, out_cols, members;
    const float *x; /* (n, d_in) fp32, the input every member shares */
    float *out;     /* (members, n, out_cols) fp32 */
    const void *weight[MAX_LAYERS]; /* in the including kernel's packed layout */
    const float *bias[MAX_LAYERS];  /* (members, padded_out[i]) fp32 */
    int64_t in[MAX_LAYERS];         /* each layer's inputs as packed (the previous layer's padded_out) */
    int64_t padded_out[MAX_LAYERS]; /* each layer's outputs, padded to a multiple of 32 */
} network;

static inline int read_addresses(PyObject *seq, int layers, void **out, const char *what) {
    if (!PyTuple_Check(seq) || PyTuple_GET_SIZE(seq) != layers) {
        PyErr_Format(PyExc_ValueError, KERNEL_NAME ".forward: %s must be a tuple of %d values", what, layers);
        return -1;
    }
    for (int i = 0; i < layers; i++) {
        out[i] = PyLong_AsVoidPtr(PyTuple_GET_ITEM(seq, i));
        if (out[i] == NULL) {
            if (!PyErr_Occurred()) PyErr_Format(PyExc_ValueError, KERNEL_NAME ".forward: %s %d is a null address", what, i);
            return -1;
        }
    }
    return 0;
}

/* sizes must be positive multiples of `multiple` */
static inline int read_sizes(PyObject *seq, int layers, int64_t *out, int64_t multiple, const char *what) {
    if (!PyTuple_Check(seq) || PyTuple_GET_SIZE(seq) != layers) {
        PyErr_Format(PyExc_ValueError, KERNEL_NAME ".forward: %s must be a tuple of %d values", what, layers);
        return -1;
    }
    for (int i = 0; i < layers; i++) {
        out[i] = PyLong_AsLongLong(PyTuple_GET_ITEM(seq, i));
        if (out[i] == -1 && PyErr_Occurred()) return -1;
        if (out[i] <= 0 || out[i] % multiple) {
            PyErr_Format(PyExc_ValueError, KERNEL_NAME ".forward: %s %d is %lld, expected a positive multiple of %lld",
                         what, i, (long long)out[i], (long long)multiple);
            return -1;
        }
    }
    return 0;
}

/* forward()'s arguments (x, n, d_in, out, out_cols, members, weights, biases, in, padded_out,
 * threads) into `net`: 0 when they describe a network the kernel can run, else -1 with a
 * ValueError naming the value and what was expected. `in_multiple`: what each layer's packed inputs
 * are a multiple of; `exact_input`: d_in must equal the first layer's inputs (else at most them:
 * the kernel pads the input itself). */
static inline int parse_network(PyObject *args, int64_t in_multiple, int exact_input, network *net, int *threads) {
    unsigned long long x, out;
    long long n, d_in, out_cols, members;
    PyObject *weights, *biases, *ins, *outs;
    if (!PyArg_ParseTuple(args, "KLLKLLOOOOi", &x, &n, &d_in, &out, &out_cols, &members, &weights, &biases, &ins,
                          &outs, threads))
        return -1;
    if (!PyTuple_Check(weights) || PyTuple_GET_SIZE(weights) < 1 || PyTuple_GET_SIZE(weights) > MAX_LAYERS) {
        PyErr_Format(PyExc_ValueError, KERNEL_NAME ".forward: weights must be a tuple of 1 to %d addresses", MAX_LAYERS);
        return -1;
    }
    net->layers = (int)PyTuple_GET_SIZE(weights);
    if (read_addresses(weights, net->layers, (void **)net->weight, "weight") < 0 ||
        read_addresses(biases, net->layers, (void **)net->bias, "bias") < 0 ||
        read_sizes(ins, net->layers, net->in, in_multiple, "packed in-features") < 0 ||
        read_sizes(outs, net->layers, net->padded_out, 32, "padded out-features") < 0)
        return -1;
    for (int i = 1; i < net->layers; i++)
        if (net->in[i] != net->padded_out[i - 1]) {
            PyErr_Format(PyExc_ValueError, KERNEL_NAME ".forward: layer %d takes %lld packed inputs, expected %lld", i,
                         (long long)net->in[i], (long long)net->padded_out[i - 1]);
            return -1;
        }
    const int64_t first_in = net->in[0], last_out = net->padded_out[net->layers - 1];
    if (n < 0 || members < 1 || d_in < 1 || (exact_input ? d_in != first_in : d_in > first_in) || out_cols < 1 ||
        out_cols > last_out || (n > 0 && (x == 0 || out == 0))) {
        PyErr_Format(PyExc_ValueError,
                     KERNEL_NAME ".forward: %lld rows of %lld inputs, %lld outputs, %lld members: expected %s%lld "
                                 "inputs, outputs <= %lld, at least one member and non-null buffers",
                     n, d_in, out_cols, members, exact_input ? "" : "at most ", (long long)first_in,
                     (long long)last_out);
        return -1;
    }
    net->n = n;
    net->d_in = d_in;
    net->out_cols = out_cols;
    net->members = members;
    net->x = (const float *)(uintptr_t)x;
    net->out = (float *)(uintptr_t)out;
    if (*threads < 1) *threads = 1;
    return 0;
}

/* run(context, first, last) over `units` work units in contiguous ranges, one per thread (a
 * thread's units share members, so their weights): 0 when every range returned 0, else -1 */
static inline int run_parallel(int64_t units, int threads, int (*run)(const void *, int64_t, int64_t), const void *context) {
    if (threads > units) threads = (int)units;
    if (threads <= 1) return run(context, 0, units);
    int failed = 0;
#pragma omp parallel num_threads(threads) reduction(| : failed)
    {
#ifdef _OPENMP
        const int64_t t = omp_get_thread_num();
#else
        const int64_t t = 0;
#endif
        failed |= run(context, units * t / threads, units * (t + 1) / threads) != 0;
    }
    return failed ? -1 : 0;
}

/* the widest layer's features (inputs as packed or padded outputs): a work unit's activation
 * buffers hold rows of this many values */
static inline int64_t widest_layer(const network *net) {
    int64_t width = 0;
    for (int i = 0; i < net->layers; i++) {
        if (net->in[i] > width) width = net->in[i];
        if (net->padded_out[i] > width) width = net->padded_out[i];
    }
    return width;
}

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>

/* lanes [0, k) of 16 */
static inline __mmask16 first16(int64_t k) { return k <= 0 ? 0 : k >= 16 ? 0xffff : (__mmask16)((1u << k) - 1u); }

/* dst (rows x kp bf16, row stride `stride`) = x's rows (rows x d_in fp32, d_in <= kp) rounded to
 * bf16 (nearest even), zeros in columns [d_in, kp): the bf16 kernels' first-layer input */
__attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16"))) static inline void rows_to_bf16(
    const float *x, int64_t d_in, int rows, uint16_t *dst, int64_t stride, int64_t kp) {
    for (int r = 0; r < rows; r++)
        for (int64_t k = 0; k < kp; k += 32) {
            const __m512 v0 = _mm512_maskz_loadu_ps(first16(d_in - k), x + r * d_in + k);
            const __m512 v1 = _mm512_maskz_loadu_ps(first16(d_in - k - 16), x + r * d_in + k + 16);
            const __mmask32 m = kp - k >= 32 ? 0xffffffffu : (__mmask32)((1u << (kp - k)) - 1u);
            _mm512_mask_storeu_epi16(dst + r * stride + k, m, (__m512i)_mm512_cvtne2ps_pbh(v1, v0));
        }
}
#endif

/* forward(net, threads) without the GIL: None, or MemoryError where a thread could not allocate
 * its scratch (never a silently incomplete output) */
static inline PyObject *call_forward(const network *net, int threads, int (*forward)(const network *, int)) {
    if (net->n == 0) Py_RETURN_NONE;
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = forward(net, threads);
    Py_END_ALLOW_THREADS
    if (status != 0) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

#endif
