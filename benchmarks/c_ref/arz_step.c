/* The reference C kernel of benchmarks/c_kernel.py: jaxtraffic's default closed loop written by hand.
 *
 * Per environment (the batch is processed one environment after the other, each one's state, delay line
 * and running sums staying in L1/L2 cache), per step n of dt:
 *   Lyapunov law h = h_bar + ((1 - keep)(v~ - V_rho rho~) - k v~) / V_h, saturated to [h_min, h_max] (NaN ->
 *   h_bar, a non-finite output refuses the step); pushed into a ring buffer of cap = max_delay_steps + 1
 *   fields; the field sent d steps ago (h_bar before t = D) is applied; one upwind ARZ step (forward Euler,
 *   inlet rho_0 = q_in / v_0, outlet speed ODE) with this step's alpha; the new state's physicality check
 *   and reward in the same pass; a state that left the physical region is refused and the plant frozen.
 *   With metrics, a second pass over the (cached) fields adds the step's integrands to per-node sums: the
 *   same ten running sums as jaxtraffic.sim.metrics (J_TTT, J_fuel, J_comfort, effort, max CFL, a_prev, a^2,
 *   a_t^2, the switch-on a_t^2, J_fuel in km/h), plus the step counters.
 * Units as jaxtraffic's: rho veh/m, v m/s, h s, the J's with rho in veh/km.
 * Build: cc -O3 -march=native -fopenmp-simd -shared -fPIC arz_step.c -o libarz_step.so (no -ffast-math:
 * IEEE semantics, so NaN checks hold; the simd pragmas let the compiler vectorise the two reductions).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* indices into the constants array (float32, computed by c_kernel.py from jaxtraffic's own functions) */
enum { RHO_BAR, V_BAR, H_BAR, V_RHO, V_H, GAIN_K, KEEP, H_MIN, H_MAX, Q_IN, L_VEH, DT, DX, TAU_ACC, TAU_M, H_M,
       N_CONSTS };
enum { J_TTT, J_FUEL, J_COMFORT, EFFORT, MAX_CFL, A_PREV, A2, AT2, SWITCH, FUEL_KMH, N_SUMS };
enum { N_ACTIVE, LAST_BAD, DIVERGED, DIVERGED_STEP, REASON, N_INTS };

static inline float fuel(float v, float a) {
    float f = 25e-3f + 24.5e-6f * v + 32.5e-9f * (v * v * v) + 125e-6f * v * a;
    return f > 0.0f ? f : 0.0f;
}

/* The reward of (rho, v) (dimensionless) and whether every node is physical (finite, 0 < rho < 1/l, v >= 0). */
static float reward_of(const float *restrict r, const float *restrict u, int n, const float *restrict c, int *ok) {
    const float irb = 1.0f / c[RHO_BAR], ivb = 1.0f / c[V_BAR], rmax = 1.0f / c[L_VEH];
    float s = 0.0f;
    int bad = 0;
#pragma omp simd reduction(+ : s) reduction(| : bad)
    for (int i = 0; i < n; i++) {
        float x = (r[i] - c[RHO_BAR]) * irb, y = (u[i] - c[V_BAR]) * ivb;
        s += x * x + y * y;
        bad |= !((r[i] > 0.0f) & (r[i] < rmax) & (u[i] >= 0.0f) & (u[i] < INFINITY));
    }
    *ok = !bad;
    return -s * (c[DX] * (1.0f / 5.0f));
}

/* One upwind ARZ step of (r, u) under the applied field ha into (r1, u1); cc, bb, inv_tau: the step's mixture
 * coefficients (alpha's). With ``want_cfl`` (a constant: the compiler specialises), the CFL number
 * max(|v|, |lambda2|) dt/dx of every node into cfl. */
static inline __attribute__((always_inline)) void arz_impl(
        const float *restrict r, const float *restrict u, const float *restrict ha, float *restrict r1,
        float *restrict u1, float *restrict cfl, int n, const float *restrict c, float alpha, float cc, float bb,
        float inv_tau, int want_cfl) {
    const float inv_dx = 1.0f / c[DX], dt = c[DT], l = c[L_VEH], cfl_fac = dt / c[DX];
#define LAM2_SRC(i)                                                                                            \
    float ir = 1.0f / r[i], ihm = (alpha + bb * ha[i]) / (cc * ha[i]);                                         \
    float lam2 = u[i] - ir * ihm, src = ((ir - l) * ihm - u[i]) * inv_tau;                                     \
    if (want_cfl) cfl[i] = (fabsf(u[i]) > fabsf(lam2) ? fabsf(u[i]) : fabsf(lam2)) * cfl_fac;
    {   /* node 0: the forward difference either way; the inlet sets its density */
        LAM2_SRC(0)
        u1[0] = u[0] + dt * (src - lam2 * ((u[1] - u[0]) * inv_dx));
    }
#pragma omp simd
    for (int i = 1; i < n - 1; i++) {
        LAM2_SRC(i)
        float fwd = (u[i + 1] - u[i]) * inv_dx, bwd = (u[i] - u[i - 1]) * inv_dx;
        u1[i] = u[i] + dt * (src - lam2 * (lam2 < 0.0f ? fwd : bwd));
        r1[i] = r[i] + dt * ((r[i - 1] * u[i - 1] - r[i] * u[i]) * inv_dx);
    }
    {   /* node N: the outlet ODE, no advection */
        LAM2_SRC(n - 1)
        (void)lam2;
        u1[n - 1] = u[n - 1] + dt * src;
        r1[n - 1] = r[n - 1] + dt * ((r[n - 2] * u[n - 2] - r[n - 1] * u[n - 1]) * inv_dx);
    }
#undef LAM2_SRC
    r1[0] = c[Q_IN] / u1[0];
}

/* The running sums of step ``step`` at node i: a the material acceleration, the rest as ``accumulate``. */
static inline __attribute__((always_inline)) void add_node(
        float *restrict s, int n, int i, float a, float u, float r, float h, float cfl, int first, int sw,
        const float *restrict c) {
    const float inv_dt = 1.0f / c[DT], w = (c[DT] * 1000.0f) * r, e = h - c[H_BAR];
    const float ap = s[A_PREV * n + i], mx = s[MAX_CFL * n + i];
    float at = (a - (first ? a : ap)) * inv_dt;
    float a2w = a * a * w, at2w = at * at * w;
    s[J_TTT * n + i] += w;
    s[J_FUEL * n + i] += fuel(u, a) * w;
    s[J_COMFORT * n + i] += (a * a + at * at) * w;
    s[EFFORT * n + i] += e * e;
    s[MAX_CFL * n + i] = cfl > mx ? cfl : mx;
    s[A_PREV * n + i] = a;
    s[A2 * n + i] += a2w;
    s[AT2 * n + i] += at2w;
    s[SWITCH * n + i] += sw ? at2w : 0.0f;
    s[FUEL_KMH * n + i] += fuel(3.6f * u, 3.6f * a) * w;
}

/* Add step ``step``'s integrands (state r, u at t_n, speed u1 at t_{n+1}, sent hs, CFL numbers) to the sums:
 * a = (v^{n+1} - v^n)/dt + v v_x (central differences inside, one-sided at the ends). */
static void accumulate(const float *restrict r, const float *restrict u, const float *restrict u1,
                       const float *restrict hs, const float *restrict cfl, float *restrict s, int n, int step,
                       int switch_step, const float *restrict c) {
    const float inv_dt = 1.0f / c[DT], inv_dx = 1.0f / c[DX], half_dx = 0.5f * inv_dx;
    const int first = step == 0, sw = step == switch_step;
    add_node(s, n, 0, (u1[0] - u[0]) * inv_dt + u[0] * ((u[1] - u[0]) * inv_dx), u[0], r[0], hs[0], cfl[0],
             first, sw, c);
#pragma omp simd
    for (int i = 1; i < n - 1; i++)
        add_node(s, n, i, (u1[i] - u[i]) * inv_dt + u[i] * ((u[i + 1] - u[i - 1]) * half_dx), u[i], r[i], hs[i],
                 cfl[i], first, sw, c);
    const int m = n - 1;
    add_node(s, n, m, (u1[m] - u[m]) * inv_dt + u[m] * ((u[m] - u[m - 1]) * inv_dx), u[m], r[m], hs[m], cfl[m],
             first, sw, c);
}

/* The law, saturated, into the sent field hs; returns whether an output was not finite. */
static int law(const float *restrict r, const float *restrict u, float *restrict hs, int n, const float *restrict c) {
    const float one_m_keep = 1.0f - c[KEEP];
    int bad_input = 0;
#pragma omp simd reduction(| : bad_input)
    for (int i = 0; i < n; i++) {
        float rt = r[i] - c[RHO_BAR], vt = u[i] - c[V_BAR];
        float h = c[H_BAR] + (one_m_keep * (vt - c[V_RHO] * rt) - c[GAIN_K] * vt) / c[V_H];
        bad_input |= !(fabsf(h) < INFINITY);
        h = h != h ? c[H_BAR] : h;
        hs[i] = h < c[H_MIN] ? c[H_MIN] : (h > c[H_MAX] ? c[H_MAX] : h);
    }
    return bad_input;
}

/* One environment, n_steps steps, in place on rho, v (n nodes). sums: N_SUMS x n floats (zeroed), or NULL
 * for the metric-free loop; ints: N_INTS out; buf: cap x n floats, work: 4 n floats of scratch. */
static void run_one(float *rho, float *v, int n, int n_steps, int d, int cap, int switch_step, const float *restrict c,
                    const float *alphas, float *sums, int *ints, float *buf, float *work) {
    float *r = rho, *u = v, *r1 = work, *u1 = work + n, *fill = work + 2 * n, *cfl = work + 3 * n;
    int head = 0, valid = 0, diverged = 0, dstep = -1, reason = 0, n_active = 0, ok;
    for (int i = 0; i < n; i++) fill[i] = c[H_BAR];
    int last_bad = reward_of(r, u, n, c, &ok) < -0.1f ? 0 : -1;
    if (!ok) { diverged = 1; dstep = 0; reason = 3; }
    const float ratio = c[TAU_ACC] / c[TAU_M];
    for (int step = 0; step < n_steps && !diverged; step++) {
        const float alpha = alphas[step];
        const float cc = alpha + (1.0f - alpha) * ratio, bb = (1.0f - alpha) * ratio / c[H_M];
        const float inv_tau = alpha / c[TAU_ACC] + (1.0f - alpha) / c[TAU_M];
        head = (head + 1) % cap;
        valid = valid + 1 < cap ? valid + 1 : cap;
        float *hs = buf + (size_t)head * n;
        int bad_input = law(r, u, hs, n, c);  /* pushed before the read: d = 0 applies this step's field */
        const float *ha = d < valid ? buf + (size_t)((head - d + cap) % cap) * n : fill;
        if (sums)
            arz_impl(r, u, ha, r1, u1, cfl, n, c, alpha, cc, bb, inv_tau, 1);
        else
            arz_impl(r, u, ha, r1, u1, cfl, n, c, alpha, cc, bb, inv_tau, 0);
        float rew = reward_of(r1, u1, n, c, &ok);
        if (!ok || bad_input) {  /* refused: frozen at its last physical state, nothing more is accumulated */
            diverged = 1; dstep = step; reason = bad_input ? 2 : 1;
            break;
        }
        if (sums) accumulate(r, u, u1, hs, cfl, sums, n, step, switch_step, c);
        n_active += 1;
        if (rew < -0.1f) last_bad = step + 1;
        float *t = r; r = r1; r1 = t;
        t = u; u = u1; u1 = t;
    }
    if (r != rho) { memcpy(rho, r, n * sizeof(float)); memcpy(v, u, n * sizeof(float)); }
    ints[N_ACTIVE] = n_active; ints[LAST_BAD] = last_bad; ints[DIVERGED] = diverged;
    ints[DIVERGED_STEP] = dstep; ints[REASON] = reason;
}

/* The whole batch: rho, v (batch x n, in place), alphas (batch x n_steps), sums (batch x N_SUMS x n, zeroed)
 * or NULL, ints (batch x N_INTS). The delay line of every environment starts empty (h_bar). Returns 0, or -1
 * if the scratch could not be allocated. */
int arz_closed_loop(int batch, int n, int n_steps, int d, int cap, int switch_step, const float *consts,
                    const float *alphas, float *rho, float *v, float *sums, int *ints) {
    float *buf = malloc(sizeof(float) * ((size_t)cap * n + 4 * (size_t)n));
    if (!buf) return -1;
    for (int b = 0; b < batch; b++)
        run_one(rho + (size_t)b * n, v + (size_t)b * n, n, n_steps, d, cap, switch_step, consts,
                alphas + (size_t)b * n_steps, sums ? sums + (size_t)b * N_SUMS * n : NULL, ints + (size_t)b * N_INTS,
                buf, buf + (size_t)cap * n);
    free(buf);
    return 0;
}
