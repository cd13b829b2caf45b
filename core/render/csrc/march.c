/* Ray marching with empty-space skipping on the CPU, for bounded fields and for warped ones (unbounded
 * scenes' contraction, forward scenes' NDC; core/field/contraction.py) with cone steps.
 *
 * Emits the samples core/render/raymarch.py's segment path emits: step k of a ray covers
 * [t_k, min(t_{k+1}, t_far)] (t_k = t_near + k*step, or past the cone knee t_c (1 + cone)^(k - k_c)), is
 * evaluated at t_start + frac*(t_end - t_start) (frac = 0.5, or a hash of (seed, ray, k) when jittered) and is
 * kept when the occupancy cell holding its (warped) evaluation point is occupied. Walking a ray one step at a
 * time would test hundreds of steps; instead an empty cell is crossed in one jump (instant-ngp's advance to the
 * next voxel), to the first step that may leave it: exactly for bounded fields, NDC (a projective map: a cell's
 * faces are planes in field space) and the contraction's linear core, and past the core by a Lipschitz bound of
 * the contraction (a step that cannot move the warped point out of its empty cell). Bounded fields follow the
 * PyTorch path's float32 operation order (built with -ffp-contract=off) and emit bit-identical samples.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

/* Plain comparisons: without -ffast-math fminf and fmaxf are library calls. Inputs here are never NaN. */
#define MINF(a, b) ((a) < (b) ? (a) : (b))
#define MAXF(a, b) ((a) > (b) ? (a) : (b))

static inline float hash_uniform(uint64_t seed, int64_t ray, int64_t k) {
    uint64_t z = seed ^ ((uint64_t)ray * 0x9E3779B97F4A7C15ull) ^ ((uint64_t)k * 0xC2B2AE3D27D4EB4Full);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull; /* splitmix64 finaliser */
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return (float)(z >> 40) * (1.0f / 16777216.0f); /* 24 bits: uniform in [0, 1) */
}

#define MAX_CASCADES 16

enum { WARP_NONE = 0, WARP_CONTRACT = 1, WARP_NDC = 2 };

typedef struct {
    int32_t kind;
    float rot[9], trans[3]; /* NDC: the reference camera's world-to-camera rotation (row-major) and translation */
    float ax, ay, near;
} Warp;

static void warp_init(Warp *w, int32_t kind, const float *params) {
    memset(w, 0, sizeof *w);
    w->kind = kind;
    if (kind == WARP_NDC) {
        memcpy(w->rot, params, 9 * sizeof(float));
        memcpy(w->trans, params + 9, 3 * sizeof(float));
        w->ax = params[12];
        w->ay = params[13];
        w->near = params[14];
    }
}

/* World-to-camera of the NDC reference camera. */
static inline void ndc_camera(const Warp *w, const float *x, float *p) {
    for (int a = 0; a < 3; a++)
        p[a] = w->rot[3 * a] * x[0] + w->rot[3 * a + 1] * x[1] + w->rot[3 * a + 2] * x[2] + w->trans[a];
}

/* The grid-space point of field-space x, as contraction.py's ContractWarp / NDCWarp. */
static inline void warp_point(const Warp *w, const float *x, float *y) {
    if (w->kind == WARP_CONTRACT) {
        const float n = MAXF(MAXF(fabsf(x[0]), MAXF(fabsf(x[1]), fabsf(x[2]))), 1e-12f);
        if (n <= 1.0f) {
            for (int a = 0; a < 3; a++) y[a] = 0.5f * x[a];
        } else {
            const float s = 2.0f - 1.0f / n;
            for (int a = 0; a < 3; a++) y[a] = 0.5f * (s * (x[a] / n));
        }
    } else if (w->kind == WARP_NDC) {
        float p[3];
        ndc_camera(w, x, p);
        const float z = MINF(p[2], -1e-6f);
        y[0] = -w->ax * p[0] / z;
        y[1] = -w->ay * p[1] / z;
        y[2] = 1.0f + 2.0f * w->near / z;
    } else {
        memcpy(y, x, 3 * sizeof(float));
    }
}

/* Where a ray's steps lie (raymarch.py's RayPlan.t_at / steps_to): uniform, or growing by (1 + cone) per step
 * past the knee k_c where the uniform step reaches cone * t. */
typedef struct {
    float tn, tf, step;
    int32_t cone_on;
    float kc, cone;
    double start, lg;
} Steps;

static inline void steps_init(Steps *s, float tn, float tf, float step, float cone) {
    s->tn = tn;
    s->tf = tf;
    s->step = step;
    s->cone_on = cone > 0.0f;
    s->cone = cone;
    s->kc = 0.0f;
    s->start = 0.0;
    s->lg = 0.0;
    if (s->cone_on) {
        const float tc = (float)((double)step / (double)cone);
        s->kc = MAXF((tc - tn) / step, 0.0f);
        s->start = (double)MAXF(tn, tc);
        s->lg = log1p((double)cone);
    }
}

static inline float t_at(const Steps *s, int64_t k) {
    if (!s->cone_on || (float)k <= s->kc) return s->tn + (float)k * s->step;
    return (float)(s->start * exp(((double)k - (double)s->kc) * s->lg));
}

/* The step whose interval holds distance `te`, less a margin for rounding: every step before it ends before te. */
static inline float step_before(const Steps *s, float te) {
    if (!s->cone_on) return floorf((te - 1e-2f * s->step - s->tn) / s->step);
    te -= 1e-2f * MAXF(s->step, te * s->cone);
    if ((double)te <= s->start) return floorf((te - s->tn) / s->step);
    return (float)floor((double)s->kc + log((double)te / s->start) / s->lg);
}

typedef struct {
    const uint8_t *occ, *coarse; /* coarse: blocks of `factor`^3 cells, set when any cell inside is occupied */
    int32_t res, cascades, factor;
    float bound, outer;
    float ext[MAX_CASCADES], scale[MAX_CASCADES], size[MAX_CASCADES]; /* half-size, cells per unit, cell size */
} Grid;

static void grid_init(Grid *g, const uint8_t *occ, const uint8_t *coarse, int32_t factor, int32_t res,
                      int32_t cascades, float bound) {
    g->occ = occ;
    g->coarse = factor > 1 ? coarse : 0;
    g->factor = factor > 1 ? factor : 1;
    g->res = res;
    g->cascades = cascades;
    g->bound = bound;
    for (int32_t c = 0; c < cascades; c++) {
        const double e = (double)bound * ldexp(1.0, c);
        g->ext[c] = (float)e;
        g->scale[c] = (float)((double)res / (2.0 * e)); /* as PyTorch: the double ratio, rounded once */
        g->size[c] = (float)(2.0 * e / res);
    }
    g->outer = g->ext[cascades - 1];
}

/* Cascade and cell of point x, as OccupancyGrid.cascade_of / _cell_index; -1 when outside every cascade. */
static inline int64_t cell_of(const Grid *g, const float *x, int32_t *casc, int32_t *ijk) {
    if (isnan(x[0] + x[1] + x[2])) return -1;
    const float m = MAXF(fabsf(x[0]), MAXF(fabsf(x[1]), fabsf(x[2])));
    if (!(m <= g->outer)) return -1;
    int32_t c = 0;
    if (g->cascades > 1) {
        const float l = ceilf(log2f(MAXF(m, 1e-30f) / g->bound));
        c = l < 0.0f ? 0 : (l > (float)(g->cascades - 1) ? g->cascades - 1 : (int32_t)l);
    }
    const float ef = g->ext[c], sc = g->scale[c];
    const int32_t r = g->res;
    int64_t flat = 0;
    for (int a = 0; a < 3; a++) {
        int32_t i = (int32_t)((x[a] + ef) * sc);
        i = i < 0 ? 0 : (i > r - 1 ? r - 1 : i);
        ijk[a] = i;
        flat = flat * r + i;
    }
    *casc = c;
    return (int64_t)c * r * r * r + flat;
}

/* Distance at which the ray (origin o, inverse direction inv) leaves box ijk of cascade c, a box being
 * `span`^3 cells; for c > 0 no farther than where it enters the inner cascade's cube, whose finer cells
 * take over there. */
static inline float box_exit(const Grid *g, const float *o, const float *inv, int32_t c, const int32_t *ijk,
                             int32_t span) {
    const float e = g->ext[c], size = g->size[c] * (float)span;
    float t_exit = INFINITY;
    for (int a = 0; a < 3; a++) {
        if (isinf(inv[a])) continue;
        const float face = (float)(ijk[a] + (inv[a] > 0.0f)) * size - e;
        t_exit = MINF(t_exit, (face - o[a]) * inv[a]);
    }
    if (c > 0) {
        const float ei = g->ext[c - 1];
        float t0 = -INFINITY, t1 = INFINITY;
        for (int a = 0; a < 3; a++) {
            if (isinf(inv[a])) {
                if (fabsf(o[a]) > ei) return t_exit;
                continue;
            }
            const float ta = (-ei - o[a]) * inv[a], tb = (ei - o[a]) * inv[a];
            t0 = MAXF(t0, MINF(ta, tb));
            t1 = MINF(t1, MAXF(ta, tb));
        }
        if (t0 <= t1 && t1 > 0.0f) t_exit = MINF(t_exit, t0);
    }
    return t_exit;
}

/* Contraction: where the ray (origin o, inverse direction inv) at x = o + t d, whose warped point y lies in the
 * empty box ijk of `span`^3 cells, may first leave it. Inside the unit cube the warp is y = x/2, so the box's
 * preimage there is a box: the exact exit, clipped to the unit cube. Outside, a bound: the contraction's
 * Jacobian has L-inf norm at most 2/n - 1.5/n^2 at |x|_inf = n >= 1 (at most 2/3, and at most 2/n for n >= 1.5,
 * where it falls), so moving s along a unit ray moves y by at most s times that over the points passed, whose
 * norm is at least n - s: a move that stays within y's distance to the box's faces stays inside. */
static inline float contract_exit(const Grid *g, const float *o, const float *inv, const float *x, const float *y,
                                  float t, const int32_t *ijk, int32_t span) {
    const float size = g->size[0] * (float)span;
    const float n = MAXF(fabsf(x[0]), MAXF(fabsf(x[1]), fabsf(x[2])));
    if (n < 1.0f) {
        float t_exit = INFINITY;
        for (int a = 0; a < 3; a++) {
            if (isinf(inv[a])) continue;
            const float face = 2.0f * ((float)(ijk[a] + (inv[a] > 0.0f)) * size - 1.0f);
            const float unit = inv[a] > 0.0f ? 1.0f : -1.0f; /* past it the warp bends */
            t_exit = MINF(t_exit, (MINF(face * unit, 1.0f) * unit - o[a]) * inv[a]);
        }
        return t_exit;
    }
    float room = INFINITY; /* L-inf distance from y to the box's faces */
    for (int a = 0; a < 3; a++) {
        const float lo = (float)ijk[a] * size - 1.0f;
        room = MINF(room, MINF(y[a] - lo, lo + size - y[a]));
    }
    if (!(room > 0.0f)) return t;
    room *= 0.999f; /* rounding in the warp */
    float s = 1.5f * room;
    const float far = room * n / (2.0f + room);
    if (far > s && n - far >= 1.5f) s = far;
    return t + s;
}

/* NDC: where the ray leaves the empty box ijk of `span`^3 cells. NDC is projective, so each face of a box in
 * NDC is a plane in field space and each coordinate runs monotonically along the ray: per axis, the face the
 * coordinate moves towards, crossed where a linear equation in t holds. p0, dp: the ray in reference-camera
 * coordinates (p = p0 + t dp). */
static inline float ndc_exit(const Grid *g, const Warp *w, const float *p0, const float *dp, float t,
                             const int32_t *ijk, int32_t span) {
    const float size = g->size[0] * (float)span;
    const float pz = p0[2] + t * dp[2];
    float t_exit = INFINITY;
    const float scale[2] = {w->ax, w->ay};
    for (int a = 0; a < 2; a++) { /* y_a = -s p_a / p_z */
        const float pa = p0[a] + t * dp[a];
        const float rate = -scale[a] * (dp[a] * pz - pa * dp[2]); /* the sign of dy_a/dt */
        if (rate == 0.0f) continue;
        const float f = (float)(ijk[a] + (rate > 0.0f)) * size - 1.0f;
        const float den = scale[a] * dp[a] + f * dp[2];
        if (den == 0.0f) continue;
        t_exit = MINF(t_exit, -(scale[a] * p0[a] + f * p0[2]) / den);
    }
    if (dp[2] != 0.0f) { /* y_z = 1 + 2 near / p_z, rising where p_z falls */
        const float f = (float)(ijk[2] + (dp[2] < 0.0f)) * size - 1.0f;
        if (f < 1.0f) t_exit = MINF(t_exit, (2.0f * w->near / (f - 1.0f) - p0[2]) / dp[2]);
    }
    return t_exit;
}

/* For the rays ids[0..n_ids), starting at step next_k[ray], emit up to `take` occupied samples each and
 * advance next_k past the last emitted (or to n_steps when the ray ran out). Outputs are packed, sorted by
 * ray then distance; returns their number (at most n_ids * take, the buffers' size). */
int64_t mr_march(const float *o, const float *d, const float *t_near, const float *t_far, const int64_t *n_steps,
                 float step, float cone, const int64_t *ids, int64_t n_ids, int64_t *next_k, int32_t take,
                 const uint8_t *occ, const uint8_t *coarse, int32_t factor, int32_t res, int32_t cascades,
                 float bound, int32_t warp_kind, const float *warp_params, int32_t jitter, uint64_t seed,
                 int64_t *out_ray, float *out_ts, float *out_te, float *out_t, float *out_x, int32_t *count,
                 int32_t threads) {
    if (cascades < 1 || cascades > MAX_CASCADES) return -1;
    if (warp_kind != WARP_NONE && (warp_kind > WARP_NDC || cascades != 1)) return -2;
    Grid g;
    grid_init(&g, occ, coarse, factor, res, cascades, bound);
    Warp w;
    warp_init(&w, warp_kind, warp_params);
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads)
    for (int64_t j = 0; j < n_ids; j++) {
        const int64_t r = ids[j];
        const float *ro = o + 3 * r, *rd = d + 3 * r;
        float inv[3];
        for (int a = 0; a < 3; a++) inv[a] = rd[a] != 0.0f ? 1.0f / rd[a] : INFINITY;
        Steps st;
        steps_init(&st, t_near[r], t_far[r], step, cone);
        float p0[3] = {0.0f, 0.0f, 0.0f}, dp[3] = {0.0f, 0.0f, 0.0f}; /* NDC: the ray in camera coordinates */
        if (w.kind == WARP_NDC) {
            ndc_camera(&w, ro, p0);
            for (int a = 0; a < 3; a++) dp[a] = w.rot[3 * a] * rd[0] + w.rot[3 * a + 1] * rd[1] + w.rot[3 * a + 2] * rd[2];
        }
        const int64_t n = n_steps[r];
        int64_t k = next_k[r];
        int32_t got = 0;
        const int64_t base = j * (int64_t)take;
        while (k < n && got < take) {
            const float ts = t_at(&st, k);
            const float te = MINF(st.cone_on ? t_at(&st, k + 1) : ts + st.step, st.tf); /* as raymarch.py */
            const float frac = jitter ? hash_uniform(seed, r, k) : 0.5f;
            const float t = ts + frac * (te - ts);
            float x[3], y[3];
            for (int a = 0; a < 3; a++) x[a] = ro[a] + t * rd[a];
            warp_point(&w, x, y);
            int32_t c, ijk[3];
            const int64_t cell = cell_of(&g, y, &c, ijk);
            if (cell >= 0 && occ[cell]) {
                const int64_t s = base + got++;
                out_ray[s] = r;
                out_ts[s] = ts;
                out_te[s] = te;
                out_t[s] = t;
                memcpy(out_x + 3 * s, x, sizeof x);
                k++;
                continue;
            }
            int64_t kn = k + 1;
            if (cell >= 0) { /* steps ending before the box's exit (less a margin for rounding) stay inside it */
                int32_t span = 1;
                if (g.coarse) { /* an empty block of cells is crossed in one jump */
                    const int32_t f = g.factor, rc = g.res / f;
                    int32_t b[3] = {ijk[0] / f, ijk[1] / f, ijk[2] / f};
                    if (!g.coarse[(((int64_t)c * rc + b[0]) * rc + b[1]) * rc + b[2]]) {
                        span = f;
                        memcpy(ijk, b, sizeof b);
                    }
                }
                const float t_exit = w.kind == WARP_CONTRACT ? contract_exit(&g, ro, inv, x, y, t, ijk, span)
                                   : w.kind == WARP_NDC ? ndc_exit(&g, &w, p0, dp, t, ijk, span)
                                   : box_exit(&g, ro, inv, c, ijk, span);
                const float jump = step_before(&st, t_exit); /* first step ending past it */
                if (jump > (float)kn && jump < (float)n) kn = (int64_t)jump;
                else if (jump >= (float)n) kn = n;
            }
            k = kn;
        }
        next_k[r] = k;
        count[j] = got;
    }
    int64_t total = 0; /* compact the per-ray slots in order (destinations never pass their sources) */
    for (int64_t j = 0; j < n_ids; j++) {
        const int64_t src = j * (int64_t)take, cnt = count[j];
        if (cnt && src != total) {
            memmove(out_ray + total, out_ray + src, cnt * sizeof *out_ray);
            memmove(out_ts + total, out_ts + src, cnt * sizeof *out_ts);
            memmove(out_te + total, out_te + src, cnt * sizeof *out_te);
            memmove(out_t + total, out_t + src, cnt * sizeof *out_t);
            memmove(out_x + 3 * total, out_x + 3 * src, 3 * cnt * sizeof *out_x);
        }
        total += cnt;
    }
    return total;
}
