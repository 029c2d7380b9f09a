/* The SiLU to fp32 accuracy, v / (1 + exp(-v)) with exp from vector_exp.h (within a few 1e-7
 * relative of torch's), shared by silu.c (the in-place pass) and fma_network.c (the fused
 * epilogue of each hidden layer): one definition, one accuracy. */
#ifndef SOFTAE_SILU_FP32_H
#define SOFTAE_SILU_FP32_H

#include <immintrin.h>

#include "vector_exp.h"

__attribute__((target("avx512f"))) static inline __m512 silu_avx512(__m512 v) {
    __m512 e = exp_avx512(_mm512_sub_ps(_mm512_setzero_ps(), v));
    return _mm512_div_ps(v, _mm512_add_ps(_mm512_set1_ps(1.0f), e));
}

__attribute__((target("avx2,fma"))) static inline __m256 silu_avx2(__m256 v) {
    __m256 e = exp_avx2(_mm256_sub_ps(_mm256_setzero_ps(), v));
    return _mm256_div_ps(v, _mm256_add_ps(_mm256_set1_ps(1.0f), e));
}

#endif
