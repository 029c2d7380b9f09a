/* The SiLU of a value whose result is rounded to bf16, shared by silu.c (the in-place pass) and
 * amx_network.c (the fused epilogue of each hidden layer): one definition, one accuracy. */
#ifndef SOFTAE_SILU_BF16GRADE_H
#define SOFTAE_SILU_BF16GRADE_H

#include <immintrin.h>

/* SiLU accurate enough for a bf16 result (fp32 value within 1e-4 relative, a bf16 ulp is 4e-3 or
 * more): exp(-v) = 2^k e^r with one-constant range reduction and e^r by its degree-4 Taylor
 * polynomial (truncation below 5e-5 relative for |r| <= ln2 / 2), and 1 / (1 + e) by the 14-bit
 * reciprocal instead of a division. The clamp keeps 1 + e below 2^126, where the reciprocal is
 * still a normal number. */
__attribute__((target("avx512f"))) static inline __m512 silu_bf16grade_avx512(__m512 v) {
    __m512 t = _mm512_max_ps(_mm512_min_ps(v, _mm512_set1_ps(87.0f)), _mm512_set1_ps(-87.0f));
    __m512 k = _mm512_roundscale_ps(_mm512_mul_ps(t, _mm512_set1_ps(-1.44269504088896341f)),
                                    _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m512 r = _mm512_fnmsub_ps(k, _mm512_set1_ps(0.693147180559945f), t); /* -k ln2 - t */
    __m512 p = _mm512_set1_ps(1.0f / 24.0f);
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f / 6.0f));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(0.5f));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f));
    __m512 e = _mm512_scalef_ps(p, k);
    return _mm512_mul_ps(v, _mm512_rcp14_ps(_mm512_add_ps(_mm512_set1_ps(1.0f), e)));
}

#endif
