/* Hand-vectorised C reference of jaxsleigh's plain fixed-step path (issue 12, part 1).
 *
 * Classical RK4 of the closed loop in the w chart, state (w1, w2, w3, p1, p2), float32, written
 * in the same order of operations as jaxsleigh.closed_loop.vector_field_w and jaxsleigh.rk4 so
 * that the final states agree to float32 rounding:
 *
 *   v      = (p1 / m, p2 / (J + m l^2))
 *   inv    = 1 / w1,  e11 = -(3 w2 + w3) inv - 0.5 w1 w3,  e21 = 2 w2 inv        (derived Q_w)
 *   u1     = -(inv (L2 w2))                      - (D11 v1 + D12 v2)
 *   u2     = -(L1 w1 + e11 (L2 w2) + e21 (L3 w3)) - (D21 v1 + (D22 + k / (w1 w1)) v2)
 *   wdot   = (v2, inv v1 + e11 v2, e21 v2)
 *   pdot   = ( a v2 - c rsqrt(eps + p1^2) v1 + u1,
 *             -a v1 - c rsqrt(eps + p2^2) v2 + u2),   a = (m l / (J + m l^2)) p2
 *   y_next = y + (h/6) (((k1 + 2 k2) + 2 k3) + k4)
 *
 * Layout: structure of arrays; the batch is cut into blocks of BLOCK (64) trajectories whose
 * state and stages (10 x 64 floats = 2.5 KiB) stay in L1 across all steps before the next block
 * is loaded. The inner loops over the 64 lanes have no branches; gcc -O3 -march=native
 * vectorises them (no -ffast-math: divisions and square roots are IEEE).
 *
 * Build: gcc -O3 -march=native [-fopenmp] -shared -fPIC rk4_w.c -o librk4_w.so  (library, ctypes)
 *        gcc -O3 -march=native [-fopenmp] -DRK4W_MAIN rk4_w.c -o rk4_w -lm      (stand-alone)
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define BLOCK 64

typedef struct {
    float m, J, l;                 /* plant */
    float d_eps, d_scale;          /* Coulomb damping c diag(1/sqrt(eps + p_i^2)) */
    float L1, L2, L3, k;           /* gains */
    float D11, D12, D21, D22;      /* D_hat */
} rk4w_params;

/* the closed-loop right-hand side on one block (BLOCK lanes), written into d[5][BLOCK] */
static inline void field(const rk4w_params *P, const float *restrict w1, const float *restrict w2,
                         const float *restrict w3, const float *restrict p1, const float *restrict p2,
                         float *restrict d1, float *restrict d2, float *restrict d3,
                         float *restrict d4, float *restrict d5)
{
    const float m = P->m, I = P->J + P->m * P->l * P->l;
    const float g = (P->m * P->l) / I;
    const float L1 = P->L1, L2 = P->L2, L3 = P->L3, k = P->k;
    const float D11 = P->D11, D12 = P->D12, D21 = P->D21, D22 = P->D22;
    const float eps = P->d_eps, c = P->d_scale;
#pragma GCC ivdep
    for (int i = 0; i < BLOCK; i++) {
        const float a1 = w1[i], a2 = w2[i], a3 = w3[i], q1 = p1[i], q2 = p2[i];
        const float v1 = q1 / m, v2 = q2 / I;
        const float inv = 1.0f / a1;
        const float e11 = -(3.0f * a2 + a3) * inv - (0.5f * a1) * a3;
        const float e21 = (2.0f * a2) * inv;
        const float Lw1 = L1 * a1, Lw2 = L2 * a2, Lw3 = L3 * a3;
        const float f1 = inv * Lw2;
        const float f2 = (Lw1 + e11 * Lw2) + e21 * Lw3;
        const float i1 = D11 * v1 + D12 * v2;
        const float i2 = D21 * v1 + (D22 + k / (a1 * a1)) * v2;
        const float u1 = -f1 - i1, u2 = -f2 - i2;
        const float ga = g * q2;
        const float r1 = (c * (1.0f / sqrtf(eps + q1 * q1))) * v1;
        const float r2 = (c * (1.0f / sqrtf(eps + q2 * q2))) * v2;
        d1[i] = v2;
        d2[i] = inv * v1 + e11 * v2;
        d3[i] = e21 * v2;
        d4[i] = (ga * v2 - r1) + u1;
        d5[i] = (-ga * v1 - r2) + u2;
    }
}

/* n_steps RK4 steps of one block held in local (L1-resident) arrays */
static void run_block(const rk4w_params *P, float y[5][BLOCK], float h, long n_steps)
{
    float k1[5][BLOCK], k2[5][BLOCK], k3[5][BLOCK], k4[5][BLOCK], t[5][BLOCK];
    const float hh = 0.5f * h, h6 = h / 6.0f;
    for (long s = 0; s < n_steps; s++) {
        field(P, y[0], y[1], y[2], y[3], y[4], k1[0], k1[1], k1[2], k1[3], k1[4]);
        for (int c = 0; c < 5; c++)
            for (int i = 0; i < BLOCK; i++) t[c][i] = y[c][i] + hh * k1[c][i];
        field(P, t[0], t[1], t[2], t[3], t[4], k2[0], k2[1], k2[2], k2[3], k2[4]);
        for (int c = 0; c < 5; c++)
            for (int i = 0; i < BLOCK; i++) t[c][i] = y[c][i] + hh * k2[c][i];
        field(P, t[0], t[1], t[2], t[3], t[4], k3[0], k3[1], k3[2], k3[3], k3[4]);
        for (int c = 0; c < 5; c++)
            for (int i = 0; i < BLOCK; i++) t[c][i] = y[c][i] + h * k3[c][i];
        field(P, t[0], t[1], t[2], t[3], t[4], k4[0], k4[1], k4[2], k4[3], k4[4]);
        for (int c = 0; c < 5; c++)
            for (int i = 0; i < BLOCK; i++)
                y[c][i] = y[c][i] + h6 * (((k1[c][i] + 2.0f * k2[c][i]) + 2.0f * k3[c][i]) + k4[c][i]);
    }
}

/* y: structure of arrays, 5 rows of n floats (row c, trajectory j at y[c * n + j]), updated in
 * place. n need not be a multiple of BLOCK (the last block is padded with a harmless state).
 * n_threads <= 0: OpenMP default; 1: serial. Returns the number of threads used. */
int rk4w_run(float *y, long n, long n_steps, float h, const rk4w_params *P, int n_threads)
{
    const long n_blocks = (n + BLOCK - 1) / BLOCK;
    int used = 1;
#ifdef _OPENMP
    if (n_threads <= 0) n_threads = omp_get_max_threads();
#pragma omp parallel for schedule(static) num_threads(n_threads)
#endif
    for (long b = 0; b < n_blocks; b++) {
        float blk[5][BLOCK];
        const long lo = b * BLOCK, cnt = (n - lo < BLOCK) ? n - lo : BLOCK;
        for (int c = 0; c < 5; c++) {
            for (long i = 0; i < BLOCK; i++)
                blk[c][i] = (i < cnt) ? y[c * n + lo + i] : (c == 0 ? 1.0f : 0.0f);
        }
        run_block(P, blk, h, n_steps);
        for (int c = 0; c < 5; c++) memcpy(&y[c * n + lo], blk[c], (size_t)cnt * sizeof(float));
#ifdef _OPENMP
        if (b == 0) used = omp_get_num_threads();
#endif
    }
    (void)n_threads;
    return used;
}

int rk4w_block(void) { return BLOCK; }

#ifdef RK4W_MAIN
/* stand-alone: rk4_w N STEPS DT THREADS < y.f32 (5 x N SoA) > y_final.f32; timing on stderr */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
int main(int argc, char **argv)
{
    if (argc < 5) { fprintf(stderr, "usage: %s N STEPS DT THREADS < y0.f32 > y.f32\n", argv[0]); return 2; }
    long n = atol(argv[1]), steps = atol(argv[2]);
    float h = (float)atof(argv[3]);
    int th = atoi(argv[4]);
    float *y = malloc(sizeof(float) * 5 * n);
    if (fread(y, sizeof(float), 5 * n, stdin) != (size_t)(5 * n)) { fprintf(stderr, "short input\n"); return 1; }
    rk4w_params P = {2.0f, 1.0f, 1.0f, 0.1f, 1.0f, 2.0f, 0.5f, 0.8f, 0.1f, 4.0f, 0.0f, 0.0f, 8.0f};
    struct timespec a, b, ca, cb;
    clock_gettime(CLOCK_MONOTONIC, &a); clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ca);
    int used = rk4w_run(y, n, steps, h, &P, th);
    clock_gettime(CLOCK_MONOTONIC, &b); clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &cb);
    double wall = (b.tv_sec - a.tv_sec) + 1e-9 * (b.tv_nsec - a.tv_nsec);
    double cpu = (cb.tv_sec - ca.tv_sec) + 1e-9 * (cb.tv_nsec - ca.tv_nsec);
    fprintf(stderr, "threads %d wall %.4f s cpu %.4f s: %.3e traj-steps/s wall, %.3e per cpu-s\n",
            used, wall, cpu, n * (double)steps / wall, n * (double)steps / cpu);
    fwrite(y, sizeof(float), 5 * n, stdout);
    return 0;
}
#endif
