/* Hand-vectorised C reference of jaxsleigh's plain fixed-step path.
 *
 * Classical RK4 of the closed loop in the w chart, state (w1, w2, w3, p1, p2), float32, written
 * in the order of operations of jaxsleigh.closed_loop.vector_field_w and jaxsleigh.rk4, so that
 * the final states agree to float32 rounding:
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
 * Layout: structure of arrays; the batch is cut into blocks of BLOCK (64 = 4 zmm) trajectories
 * whose state, stages and RK4 sum (15 x 64 floats = 3.75 KiB) stay in L1 across all steps before
 * the next block is loaded. Each stage is one branch-free loop over the lanes that forms the stage
 * point, evaluates the field and accumulates the RK4 sum in registers; gcc -O3 -march=native
 * vectorises it with 64-byte vectors (-fopt-info-vec). No -ffast-math: every division and square
 * root is an IEEE (correctly rounded) instruction; -fno-math-errno only lets gcc vectorise sqrtf.
 *
 * Speed is bound by the divide/square-root unit (one per core, shared: ~10 cycles per zmm
 * division, ~12 per zmm square root on this machine, measured by experiments/performance/c_reference/
 * divsqrt_micro.c), not by memory or by the ~50 other vector operations per evaluation. So the
 * default form uses as few of them as the arithmetic allows without leaving float32 rounding:
 *   - p1 / m and p2 / (J + m l^2) are multiplications by reciprocals computed once (XLA itself
 *     does this for J + m l^2);
 *   - k / (w1 w1) is (k inv) inv with inv = 1 / w1 already needed by Q_w;
 * leaving 3 divisions and 2 square roots per evaluation (1 / w1 and the two 1 / sqrt). This moves
 * final states by float32 rounding only (docs/performance_fastpath.md gives the agreement).
 * Variants, for the measurements only:
 *   -DRK4W_STRICT       the literal form: 6 divisions + 2 square roots per evaluation (the earlier
 *                       reference; bitwise its results with -ffp-contract=off, with gcc's default
 *                       FMA contraction ~3/4 of the rows bitwise, the rest within rounding);
 *   -DRK4W_SHARED_RECIP one division for 1 / w1 and both 1 / sqrt: R = 1 / (w1 s1 s2), s_i =
 *                       sqrt(eps + p_i^2) (2 square roots + 1 division): a few ulp, and it overflows
 *                       or gives NaN where the literal form gives inf or 0 (w1 = 0, |w1 p1 p2| > 1e38);
 *   -DRK4W_RSQRT_NR     1 / sqrt by the hardware estimate (vrsqrt14ps, 2^-14) and one Newton step,
 *                       as XLA:CPU computes lax.rsqrt: 1 division per evaluation; not correctly
 *                       rounded (a few ulp), so not the default reference.
 *
 * Build: gcc -O3 -march=native -fno-math-errno [-fopenmp] -shared -fPIC rk4_w.c -o librk4_w.so -lm
 *        gcc -O3 -march=native -fno-math-errno [-fopenmp] -DRK4W_MAIN rk4_w.c -o rk4_w -lm
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif
#ifdef RK4W_RSQRT_NR
#include <immintrin.h>
#endif

#ifndef BLOCK
#define BLOCK 64
#endif

typedef struct {
    float m, J, l;                 /* plant */
    float d_eps, d_scale;          /* Coulomb damping c diag(1/sqrt(eps + p_i^2)) */
    float L1, L2, L3, k;           /* gains */
    float D11, D12, D21, D22;      /* D_hat */
} rk4w_params;

/* loop-invariant constants of the field */
typedef struct {
    float m, I, rm, rI, g, L1, L2, L3, k, D11, D12, D21, D22, eps, c;
} consts;

static consts make_consts(const rk4w_params *P)
{
    consts K;
    K.m = P->m;
    K.I = P->J + P->m * P->l * P->l;
    K.rm = 1.0f / K.m;
    K.rI = 1.0f / K.I;
    K.g = (P->m * P->l) / K.I;
    K.L1 = P->L1; K.L2 = P->L2; K.L3 = P->L3; K.k = P->k;
    K.D11 = P->D11; K.D12 = P->D12; K.D21 = P->D21; K.D22 = P->D22;
    K.eps = P->d_eps; K.c = P->d_scale;
    return K;
}

#ifdef RK4W_RSQRT_NR
/* one Newton step on the 2^-14 estimate, the form XLA:CPU emits for lax.rsqrt */
static inline void rsqrt_block(const float *restrict x, float *restrict r)
{
    for (int i = 0; i < BLOCK; i += 16) {
        __m512 a = _mm512_loadu_ps(x + i);
        __m512 e = _mm512_rsqrt14_ps(a);
        __m512 t = _mm512_mul_ps(_mm512_mul_ps(a, e), e);                  /* a e^2 */
        e = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5f), e),
                          _mm512_sub_ps(_mm512_set1_ps(3.0f), t));         /* e (3 - a e^2) / 2 */
        _mm512_storeu_ps(r + i, e);
    }
}
#endif

/* the closed-loop field at one lane's state (a1..q2), into d1..d5 */
#if defined(RK4W_SHARED_RECIP)
#define RSQ1 rsq1
#define RSQ2 rsq2
#elif defined(RK4W_RSQRT_NR)
#define RSQ1 rs1[i]
#define RSQ2 rs2[i]
#else
#define RSQ1 (1.0f / sqrtf(K->eps + q1 * q1))
#define RSQ2 (1.0f / sqrtf(K->eps + q2 * q2))
#endif
#ifdef RK4W_STRICT
#define VEL1 (q1 / K->m)
#define VEL2 (q2 / K->I)
#define KW2 (K->k / (a1 * a1))
#else
#define VEL1 (q1 * K->rm)
#define VEL2 (q2 * K->rI)
#define KW2 ((K->k * inv) * inv)
#endif
#ifdef RK4W_SHARED_RECIP
#define INVDEF const float s1_ = sqrtf(K->eps + (q1) * (q1)), s2_ = sqrtf(K->eps + (q2) * (q2)); \
    const float s12_ = s1_ * s2_, R_ = 1.0f / ((a1) * s12_);                              \
    const float inv = s12_ * R_, rsq1 = ((a1) * s2_) * R_, rsq2 = ((a1) * s1_) * R_;
#else
#define INVDEF const float inv = 1.0f / (a1);
#endif
#define FIELD(a1, a2, a3, q1, q2, d1, d2, d3, d4, d5)                                       \
    do {                                                                                    \
        const float v1 = VEL1, v2 = VEL2;                                                   \
        INVDEF                                                                              \
        const float e11 = -(3.0f * (a2) + (a3)) * inv - (0.5f * (a1)) * (a3);               \
        const float e21 = (2.0f * (a2)) * inv;                                              \
        const float Lw1 = K->L1 * (a1), Lw2 = K->L2 * (a2), Lw3 = K->L3 * (a3);             \
        const float f1 = inv * Lw2;                                                         \
        const float f2 = (Lw1 + e11 * Lw2) + e21 * Lw3;                                     \
        const float i1 = K->D11 * v1 + K->D12 * v2;                                         \
        const float i2 = K->D21 * v1 + (K->D22 + KW2) * v2;                                 \
        const float u1 = -f1 - i1, u2 = -f2 - i2;                                           \
        const float ga = K->g * (q2);                                                       \
        const float r1 = (K->c * RSQ1) * v1;                                                \
        const float r2 = (K->c * RSQ2) * v2;                                                \
        d1 = v2;                                                                            \
        d2 = inv * v1 + e11 * v2;                                                           \
        d3 = e21 * v2;                                                                      \
        d4 = (ga * v2 - r1) + u1;                                                           \
        d5 = (-ga * v1 - r2) + u2;                                                          \
    } while (0)

/* One RK4 stage over a block: the stage point t = y + a kin (kin = NULL: t = y), its field
 * k = f(t) (stored in kout when kout != NULL), and the RK4 sum: mode 0: s = k; 1: s += 2 k;
 * 2: y += h6 (s + k). Same operation order as y + (h/6) (((k1 + 2 k2) + 2 k3) + k4). */
static inline void stage(const consts *restrict K, float (*restrict y)[BLOCK], const float (*restrict kin)[BLOCK],
                         float a, float (*restrict kout)[BLOCK], float (*restrict s)[BLOCK], int mode, float h6)
{
#ifdef RK4W_RSQRT_NR
    float x1[BLOCK], x2[BLOCK], rs1[BLOCK], rs2[BLOCK];
    for (int i = 0; i < BLOCK; i++) {
        const float q1 = kin ? y[3][i] + a * kin[3][i] : y[3][i];
        const float q2 = kin ? y[4][i] + a * kin[4][i] : y[4][i];
        x1[i] = K->eps + q1 * q1;
        x2[i] = K->eps + q2 * q2;
    }
    rsqrt_block(x1, rs1);
    rsqrt_block(x2, rs2);
#endif
#pragma GCC ivdep
    for (int i = 0; i < BLOCK; i++) {
        float a1 = y[0][i], a2 = y[1][i], a3 = y[2][i], q1 = y[3][i], q2 = y[4][i];
        if (kin) {
            a1 = a1 + a * kin[0][i]; a2 = a2 + a * kin[1][i]; a3 = a3 + a * kin[2][i];
            q1 = q1 + a * kin[3][i]; q2 = q2 + a * kin[4][i];
        }
        float d1, d2, d3, d4, d5;
        FIELD(a1, a2, a3, q1, q2, d1, d2, d3, d4, d5);
        if (kout) { kout[0][i] = d1; kout[1][i] = d2; kout[2][i] = d3; kout[3][i] = d4; kout[4][i] = d5; }
        if (mode == 0) {
            s[0][i] = d1; s[1][i] = d2; s[2][i] = d3; s[3][i] = d4; s[4][i] = d5;
        } else if (mode == 1) {
            s[0][i] = s[0][i] + 2.0f * d1; s[1][i] = s[1][i] + 2.0f * d2; s[2][i] = s[2][i] + 2.0f * d3;
            s[3][i] = s[3][i] + 2.0f * d4; s[4][i] = s[4][i] + 2.0f * d5;
        } else {
            y[0][i] = y[0][i] + h6 * (s[0][i] + d1); y[1][i] = y[1][i] + h6 * (s[1][i] + d2);
            y[2][i] = y[2][i] + h6 * (s[2][i] + d3); y[3][i] = y[3][i] + h6 * (s[3][i] + d4);
            y[4][i] = y[4][i] + h6 * (s[4][i] + d5);
        }
    }
}

/* n_steps RK4 steps of one block held in local (L1-resident) arrays */
static void run_block(const consts *K, float y[5][BLOCK], float h, long n_steps)
{
    float ka[5][BLOCK], kb[5][BLOCK], s[5][BLOCK];
    const float hh = 0.5f * h, h6 = h / 6.0f;
    for (long n = 0; n < n_steps; n++) {
        stage(K, y, NULL, 0.0f, ka, s, 0, h6);      /* k1 -> ka, s = k1            */
        stage(K, y, ka, hh, kb, s, 1, h6);          /* k2 -> kb, s = k1 + 2 k2     */
        stage(K, y, kb, hh, ka, s, 1, h6);          /* k3 -> ka, s += 2 k3         */
        stage(K, y, ka, h, NULL, s, 2, h6);         /* k4, y += h6 (s + k4)        */
    }
}

/* y: structure of arrays, 5 rows of n floats (row c, trajectory j at y[c * n + j]), updated in
 * place. n need not be a multiple of BLOCK (the last block is padded with a harmless state).
 * n_threads <= 0: OpenMP default; 1: serial. Returns the number of threads used. */
int rk4w_run(float *y, long n, long n_steps, float h, const rk4w_params *P, int n_threads)
{
    const long n_blocks = (n + BLOCK - 1) / BLOCK;
    const consts K = make_consts(P);
    int used = 1;
#ifdef _OPENMP
    if (n_threads <= 0) n_threads = omp_get_max_threads();
#pragma omp parallel for schedule(static) num_threads(n_threads)
#endif
    for (long b = 0; b < n_blocks; b++) {
        float blk[5][BLOCK] __attribute__((aligned(64)));
        const long lo = b * BLOCK, cnt = (n - lo < BLOCK) ? n - lo : BLOCK;
        for (int c = 0; c < 5; c++) {
            for (long i = 0; i < BLOCK; i++)
                blk[c][i] = (i < cnt) ? y[c * n + lo + i] : (c == 0 ? 1.0f : 0.0f);
        }
        run_block(&K, blk, h, n_steps);
        for (int c = 0; c < 5; c++) memcpy(&y[c * n + lo], blk[c], (size_t)cnt * sizeof(float));
#ifdef _OPENMP
        if (b == 0) used = omp_get_num_threads();
#endif
    }
    (void)n_threads;
    return used;
}

int rk4w_block(void) { return BLOCK; }

/* divider operations (divisions + square roots) per field evaluation in this build */
int rk4w_divider_ops(void)
{
#if defined(RK4W_STRICT)
    return 8;
#elif defined(RK4W_SHARED_RECIP)
    return 3;
#elif defined(RK4W_RSQRT_NR)
    return 1;
#else
    return 5;
#endif
}

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
