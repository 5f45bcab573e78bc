/* Throughput of the divide / square-root unit on one core (what bounds the C reference).
 *
 * Build and run:  gcc -O2 -march=native experiments/performance/c_reference/divsqrt_micro.c -o divsqrt_micro && ./divsqrt_micro
 *
 * The clock is estimated from a dependent chain of FMAs (4 cycles each on Intel since Skylake);
 * then 8 independent chains of vdivps / vsqrtps (AVX-512 and AVX2) give cycles per instruction.
 * CPU time (CLOCK_PROCESS_CPUTIME_ID), so a shared machine's load matters less. */
#include <immintrin.h>
#include <stdio.h>
#include <time.h>

static double cpu(void)
{
    struct timespec t;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

#define KEEP8(a) __asm__ volatile("" ::"v"(a[0]), "v"(a[1]), "v"(a[2]), "v"(a[3]), "v"(a[4]), "v"(a[5]), "v"(a[6]), "v"(a[7]))

int main(void)
{
    const long N = 20000000;
    __m512 a[8], b = _mm512_set1_ps(1.0000001f), one = _mm512_set1_ps(1.0f);
    __m256 c[8], d = _mm256_set1_ps(1.0000001f);
    for (int i = 0; i < 8; i++) { a[i] = _mm512_set1_ps(1.5f + i); c[i] = _mm256_set1_ps(1.5f + i); }
    __m512 x = one;
    double t0 = cpu();
    for (long i = 0; i < N; i++) { x = _mm512_fmadd_ps(x, b, one); __asm__ volatile("" ::"v"(x)); }
    double t1 = cpu();
    const double hz = 4.0 * N / (t1 - t0), n_ops = 2.0 * N;
    printf("clock (dependent FMA chain, 4 cycles each): %.2f GHz\n", hz / 1e9);
    t0 = cpu();
    for (long i = 0; i < N / 4; i++) { for (int j = 0; j < 8; j++) a[j] = _mm512_div_ps(b, a[j]); KEEP8(a); }
    t1 = cpu();
    printf("vdivps zmm:  %5.2f cycles each, %.2e lane-divisions per CPU s\n", hz * (t1 - t0) / n_ops, 16 * n_ops / (t1 - t0));
    t0 = cpu();
    for (long i = 0; i < N / 4; i++) { for (int j = 0; j < 8; j++) a[j] = _mm512_sqrt_ps(a[j]); KEEP8(a); }
    t1 = cpu();
    printf("vsqrtps zmm: %5.2f cycles each, %.2e lane-square-roots per CPU s\n", hz * (t1 - t0) / n_ops, 16 * n_ops / (t1 - t0));
    t0 = cpu();
    for (long i = 0; i < N / 4; i++) {
        for (int j = 0; j < 4; j++) { a[j] = _mm512_div_ps(b, a[j]); a[j + 4] = _mm512_sqrt_ps(a[j + 4]); }
        KEEP8(a);
    }
    t1 = cpu();
    printf("vdivps + vsqrtps zmm, mixed: %5.2f cycles each (one shared unit)\n", hz * (t1 - t0) / n_ops);
    t0 = cpu();
    for (long i = 0; i < N / 4; i++) { for (int j = 0; j < 8; j++) c[j] = _mm256_div_ps(d, c[j]); KEEP8(c); }
    t1 = cpu();
    printf("vdivps ymm:  %5.2f cycles each, %.2e lane-divisions per CPU s (same per lane as zmm)\n",
           hz * (t1 - t0) / n_ops, 8 * n_ops / (t1 - t0));
    float sink[16];
    _mm512_storeu_ps(sink, x);
    return sink[0] == 12345.0f;
}
