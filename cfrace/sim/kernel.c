/* cfrace fused CPU kernel: the same model as cfrace/sim/simulator.py::_substep (the torch
 * reference). Built at first use by cfrace/sim/ckernel.py with the system C compiler; the torch
 * path is the fallback and the reference the tests compare against.
 *
 * Vectorised across drones: the W x D drones are cut into blocks of whole worlds (NB lanes, at
 * most NB / D worlds per block). A block's state is gathered into structure-of-arrays locals, all
 * `substeps` physics steps run on it as `omp simd` loops over the lanes with branch-free code
 * (selects instead of early-outs), then it is scattered back. Lanes are drone-major (lane
 * d * WB + w holds drone d of the block's world w, WB = NB / D), so that a drone's partner in its
 * world is a fixed lane offset away. Unused lanes are crashed dummies.
 * Every lane runs the same instructions and only reads its own world, so results do not depend on
 * the block a drone lands in, on the batch size or on the number of threads.
 * Layouts: all arrays contiguous, row-major, shapes as in simulator.py (W worlds, D drones). */
#include <math.h>
#include <stdint.h>
#include <string.h>

enum { R_NONE = 0, R_FLOOR = 1, R_CEILING = 2, R_ARENA = 3, R_GATE = 4, R_CONTACT = 5 };
#define MAXD 16
#define MAXG 256
#define NB 16 /* lanes per block: a multiple of the vector width, so every lane takes the same path */
/* plain compares: one min/max instruction each (fminf/fmaxf carry NaN rules that cost a call) */
#define MINF(a, b) ((a) < (b) ? (a) : (b))
#define MAXF(a, b) ((a) > (b) ? (a) : (b))
#define CLAMP(x, lo, hi) MINF(MAXF(x, lo), hi)
#define SIMD _Pragma("omp simd")
/* the gate rule's constants (cfrace/sim/gates.py): ckernel.py passes them at build time as -D
 * flags, so that they are literals to the compiler and defined only in Python (read from cst[]
 * they compiled to other machine code, a few per cent slower: docs/benchmarks.md) */
#if !defined(PASS_RADIUS) || !defined(PASS_HALF) || !defined(FRAME_HIT_HALF)
#error "build through cfrace/sim/ckernel.py: it defines PASS_RADIUS, PASS_HALF, FRAME_HIT_HALF"
#endif

/* constants: indices into cst[] (filled by ckernel.py, keep in sync) */
enum {
  C_DT, C_MASS, C_IX, C_IY, C_IZ, C_KETA, C_KRATIO, C_RX0, C_RX1, C_RX2, C_RX3, C_RY0, C_RY1, C_RY2, C_RY3,
  C_DIR0, C_DIR1, C_DIR2, C_DIR3, C_MIX0, /* 16 values */ C_WMIN = C_MIX0 + 16, C_WMAX, C_IL0, C_IL1, C_IL2,
  C_G, C_RADIUS, C_ZREST, C_AX0, C_AX1, C_AY0, C_AY1, C_AZ, C_OUTER, C_GRACE, C_FLOORZ, C_IMPACT, C_LONGC,
  C_ARENA_ON, C_COUNT
};

/* the tensors, in the order ckernel.py passes their addresses (keep in sync) */
enum {
  P_CST, P_POS, P_VEL, P_QUAT, P_OMEGA, P_MOTOR, P_PID_INT, P_OMEGA_PREV,
  P_TARGET, P_GATES_PASSED, P_LAPS, P_LAP_START, P_LAP_LAST, P_CRASHED, P_REASON, P_CONTACT_TIME, P_TIME,
  P_KP, P_KI, P_KD, P_K_AERO, P_ALPHA, P_GATES, P_BAR_C, P_BAR_H, P_BAR_COS, P_BAR_SIN,
  P_OB_C, P_OB_H, P_OB_COS, P_OB_SIN, P_THRUST, P_RATES,
  P_EV_GATES, P_EV_LAPS, P_EV_CRASHED, P_EV_CONTACT, P_EV_REASON, P_COUNT
};

#define A64 __attribute__((aligned(64)))
typedef struct {
  /* drone state */
  float p[3][NB] A64, v[3][NB] A64, q[4][NB] A64, om[3][NB] A64, mo[4][NB] A64, pi[3][NB] A64, op[3][NB] A64;
  /* parameters and command, fixed during the call */
  float kp[3][NB] A64, ki[3][NB] A64, kd[3][NB] A64, ka[3][NB] A64, alpha[NB] A64, thr[NB] A64, rate[3][NB] A64;
  /* race state */
  int32_t tgt[NB] A64, gpm[NB] A64, crashed[NB] A64, reason[NB] A64;
  float ct[NB] A64, lap_start[NB] A64, lap_last[NB] A64, t[NB] A64;
  /* events of this call */
  int32_t ev_g[NB] A64, ev_l[NB] A64, ev_c[NB] A64, ev_ct[NB] A64;
  /* per-substep scratch */
  float np[3][NB] A64, nv[3][NB] A64, dp[3][NB] A64, dv[3][NB] A64;
  float gx[NB] A64, gy[NB] A64, gz[NB] A64, gc[NB] A64, gs[NB] A64; /* pose of the target gate */
  float rp[3][2 * NB] A64, rv[3][2 * NB] A64;                         /* np, nv twice: rotations */
  int32_t rlive[2 * NB] A64;
  int32_t live[NB] A64, why[NB] A64, contact[NB] A64, passed[NB] A64, hit[NB] A64, near[NB] A64;
} Block;

typedef struct {
  int D, G, K, nug, WB;             /* WB: worlds per block */
  int ug[MAXG];                    /* distinct gate poses (a track may pass one gate twice) */
  float gcos[MAXG], gsin[MAXG];
  const float *cst, *gates, *bar_c, *bar_h, *bar_cos, *bar_sin, *ob_c, *ob_h, *ob_cos, *ob_sin;
} Setup;

static inline int finite_bits(float x) {
  uint32_t u;
  memcpy(&u, &x, sizeof(u));
  return (u & 0x7f800000u) != 0x7f800000u;
}

/* gather worlds [w0, w0 + nw) into b; lanes beyond nw * D become crashed dummies */
/* the pose of each lane's target gate */
static void target_poses(Block *b, const Setup *S) {
  for (int l = 0; l < NB; l++) {
    const int g = b->tgt[l];
    b->gx[l] = S->gates[4 * g]; b->gy[l] = S->gates[4 * g + 1]; b->gz[l] = S->gates[4 * g + 2];
    b->gc[l] = S->gcos[g]; b->gs[l] = S->gsin[g];
  }
}

static void gather(Block *b, void *const *P, const Setup *S, int w0, int nw) {
  const int D = S->D;
  const float *pos = P[P_POS], *vel = P[P_VEL], *quat = P[P_QUAT], *omega = P[P_OMEGA], *motor = P[P_MOTOR];
  const float *pid = P[P_PID_INT], *oprev = P[P_OMEGA_PREV], *kp = P[P_KP], *ki = P[P_KI], *kd = P[P_KD];
  const float *ka = P[P_K_AERO], *alpha = P[P_ALPHA], *thrust = P[P_THRUST], *rates = P[P_RATES];
  const int64_t *target = P[P_TARGET], *gates_passed = P[P_GATES_PASSED], *reason = P[P_REASON];
  const uint8_t *crashed = P[P_CRASHED];
  const float *lap_start = P[P_LAP_START], *lap_last = P[P_LAP_LAST], *ct = P[P_CONTACT_TIME], *time = P[P_TIME];
  memset(b, 0, sizeof(*b));
  for (int l = 0; l < NB; l++) { b->q[0][l] = 1.f; b->p[2][l] = 1.f; b->crashed[l] = 1; } /* dummies */
  for (int i = 0; i < D * nw; i++) {
    const int d = i / nw, w = i - d * nw, l = d * S->WB + w; /* drone-major lanes */
    const int64_t n = (int64_t)(w0 + w) * D + d;
    for (int k = 0; k < 3; k++) {
      b->p[k][l] = pos[3 * n + k]; b->v[k][l] = vel[3 * n + k]; b->om[k][l] = omega[3 * n + k];
      b->pi[k][l] = pid[3 * n + k]; b->op[k][l] = oprev[3 * n + k];
      b->kp[k][l] = kp[3 * n + k]; b->ki[k][l] = ki[3 * n + k]; b->kd[k][l] = kd[3 * n + k];
      b->ka[k][l] = ka[3 * n + k];
    }
    for (int k = 0; k < 4; k++) { b->q[k][l] = quat[4 * n + k]; b->mo[k][l] = motor[4 * n + k]; }
    /* a non-finite command means motors off (thrust 0, rates 0) */
    int ok = finite_bits(thrust[n]) && finite_bits(rates[3 * n]) && finite_bits(rates[3 * n + 1])
             && finite_bits(rates[3 * n + 2]);
    b->thr[l] = ok ? thrust[n] : 0.f;
    for (int k = 0; k < 3; k++) b->rate[k][l] = ok ? rates[3 * n + k] : 0.f;
    b->alpha[l] = alpha[n];
    b->tgt[l] = (int32_t)target[n];
    b->gpm[l] = (int32_t)(gates_passed[n] % S->G);
    b->crashed[l] = crashed[n];
    b->reason[l] = (int32_t)reason[n];
    b->ct[l] = ct[n]; b->lap_start[l] = lap_start[n]; b->lap_last[l] = lap_last[n];
    b->t[l] = time[w0 + w];
  }
  target_poses(b, S);
}

static void scatter(const Block *b, void *const *P, const Setup *S, int w0, int nw) {
  const int D = S->D;
  float *pos = P[P_POS], *vel = P[P_VEL], *quat = P[P_QUAT], *omega = P[P_OMEGA], *motor = P[P_MOTOR];
  float *pid = P[P_PID_INT], *oprev = P[P_OMEGA_PREV];
  int64_t *target = P[P_TARGET], *gates_passed = P[P_GATES_PASSED], *laps = P[P_LAPS], *reason = P[P_REASON];
  uint8_t *crashed = P[P_CRASHED], *ev_crashed = P[P_EV_CRASHED], *ev_contact = P[P_EV_CONTACT];
  float *lap_start = P[P_LAP_START], *lap_last = P[P_LAP_LAST], *ct = P[P_CONTACT_TIME], *time = P[P_TIME];
  int64_t *ev_gates = P[P_EV_GATES], *ev_laps = P[P_EV_LAPS], *ev_reason = P[P_EV_REASON];
  for (int i = 0; i < D * nw; i++) {
    const int d = i / nw, w = i - d * nw, l = d * S->WB + w; /* drone-major lanes */
    const int64_t n = (int64_t)(w0 + w) * D + d;
    for (int k = 0; k < 3; k++) {
      pos[3 * n + k] = b->p[k][l]; vel[3 * n + k] = b->v[k][l]; omega[3 * n + k] = b->om[k][l];
      pid[3 * n + k] = b->pi[k][l]; oprev[3 * n + k] = b->op[k][l];
    }
    for (int k = 0; k < 4; k++) { quat[4 * n + k] = b->q[k][l]; motor[4 * n + k] = b->mo[k][l]; }
    target[n] = b->tgt[l];
    gates_passed[n] += b->ev_g[l];
    laps[n] += b->ev_l[l];
    crashed[n] = (uint8_t)b->crashed[l];
    reason[n] = b->reason[l];
    ct[n] = b->ct[l]; lap_start[n] = b->lap_start[l]; lap_last[n] = b->lap_last[l];
    ev_gates[n] = b->ev_g[l]; ev_laps[n] = b->ev_l[l];
    ev_crashed[n] = (uint8_t)b->ev_c[l]; ev_contact[n] = (uint8_t)b->ev_ct[l];
    ev_reason[n] = b->ev_c[l] ? b->reason[l] : 0;
    if (d == 0) time[w0 + w] = b->t[l];
  }
}

/* dynamics, floor, arena, ceiling and the target gate's plane, for every lane */
static void physics(Block *restrict b, const Setup *S) {
  const float *cs = S->cst;
  const float dt = cs[C_DT], inv_dt = (float)(1.0 / cs[C_DT]), inv_m = (float)(1.0 / cs[C_MASS]), h = 0.5f * dt;
  const float I0 = cs[C_IX], I1 = cs[C_IY], I2 = cs[C_IZ], keta = cs[C_KETA], inv_keta = (float)(1.0 / cs[C_KETA]);
  const float il0 = cs[C_IL0], il1 = cs[C_IL1], il2 = cs[C_IL2], wmin = cs[C_WMIN], wmax = cs[C_WMAX];
  const float zrest = cs[C_ZREST], impact = cs[C_IMPACT], grace = cs[C_GRACE], floorz = cs[C_FLOORZ];
  const float ax0 = cs[C_AX0], ax1 = cs[C_AX1], ay0 = cs[C_AY0], ay1 = cs[C_AY1], az = cs[C_AZ], g = cs[C_G];
  const float outer = cs[C_OUTER], arena_on = cs[C_ARENA_ON], kratio = cs[C_KRATIO];
  const float *mix = cs + C_MIX0, *rx = cs + C_RX0, *ry = cs + C_RY0, *dir = cs + C_DIR0;
  SIMD
  for (int l = 0; l < NB; l++) {
    const int live = !b->crashed[l];
    const float w0 = b->om[0][l], w1 = b->om[1][l], w2 = b->om[2][l];
    /* body-rate PID, derivative on the measured rate */
    const float e0 = b->rate[0][l] - w0, e1 = b->rate[1][l] - w1, e2 = b->rate[2][l] - w2;
    const float i0 = CLAMP(b->pi[0][l] + e0 * dt, -il0, il0), i1 = CLAMP(b->pi[1][l] + e1 * dt, -il1, il1);
    const float i2 = CLAMP(b->pi[2][l] + e2 * dt, -il2, il2);
    const float td0 = I0 * (b->kp[0][l] * e0 + b->ki[0][l] * i0 - b->kd[0][l] * ((w0 - b->op[0][l]) * inv_dt));
    const float td1 = I1 * (b->kp[1][l] * e1 + b->ki[1][l] * i1 - b->kd[1][l] * ((w1 - b->op[1][l]) * inv_dt));
    const float td2 = I2 * (b->kp[2][l] * e2 + b->ki[2][l] * i2 - b->kd[2][l] * ((w2 - b->op[2][l]) * inv_dt));
    /* mixer and first-order motors */
    const float thr = b->thr[l], alpha = b->alpha[l];
    float f0, f1, f2, f3, m0, m1, m2, m3;
#define MOTOR(r, f, m)                                                                                           \
    {                                                                                                            \
      const float fd = thr * mix[4 * r] + td0 * mix[4 * r + 1] + td1 * mix[4 * r + 2] + td2 * mix[4 * r + 3];  \
      const float wd = CLAMP(sqrtf(MAXF(fd, 0.f) * inv_keta), wmin, wmax);                                     \
      m = b->mo[r][l] + (wd - b->mo[r][l]) * alpha;                                                              \
      b->mo[r][l] = live ? m : 0.f;                                                                              \
      f = keta * m * m;                                                                                          \
    }
    MOTOR(0, f0, m0) MOTOR(1, f1, m1) MOTOR(2, f2, m2) MOTOR(3, f3, m3)
#undef MOTOR
    const float msum = m0 + m1 + m2 + m3;
    const float fz = f0 + f1 + f2 + f3;
    const float tx = f0 * ry[0] + f1 * ry[1] + f2 * ry[2] + f3 * ry[3];
    const float ty = -(f0 * rx[0] + f1 * rx[1] + f2 * rx[2] + f3 * rx[3]);
    const float tz = kratio * (f0 * dir[0] + f1 * dir[1] + f2 * dir[2] + f3 * dir[3]);
    /* rotation from the current attitude; drag in the body frame */
    const float qw = b->q[0][l], qx = b->q[1][l], qy = b->q[2][l], qz = b->q[3][l];
    const float R00 = 1 - 2 * (qy * qy + qz * qz), R01 = 2 * (qx * qy - qw * qz), R02 = 2 * (qx * qz + qw * qy);
    const float R10 = 2 * (qx * qy + qw * qz), R11 = 1 - 2 * (qx * qx + qz * qz), R12 = 2 * (qy * qz - qw * qx);
    const float R20 = 2 * (qx * qz - qw * qy), R21 = 2 * (qy * qz + qw * qx), R22 = 1 - 2 * (qx * qx + qy * qy);
    const float vx = b->v[0][l], vy = b->v[1][l], vz = b->v[2][l];
    const float fb0 = -msum * b->ka[0][l] * (R00 * vx + R10 * vy + R20 * vz);
    const float fb1 = -msum * b->ka[1][l] * (R01 * vx + R11 * vy + R21 * vz);
    const float fb2 = -msum * b->ka[2][l] * (R02 * vx + R12 * vy + R22 * vz) + fz;
    const float a0 = (R00 * fb0 + R01 * fb1 + R02 * fb2) * inv_m;
    const float a1 = (R10 * fb0 + R11 * fb1 + R12 * fb2) * inv_m;
    const float a2 = (R20 * fb0 + R21 * fb1 + R22 * fb2) * inv_m - g;
    /* Euler's equation, semi-implicit Euler */
    const float iw0 = I0 * w0, iw1 = I1 * w1, iw2 = I2 * w2;
    const float n0 = w0 + (tx - (w1 * iw2 - w2 * iw1)) * (1.f / I0) * dt;
    const float n1 = w1 + (ty - (w2 * iw0 - w0 * iw2)) * (1.f / I1) * dt;
    const float n2 = w2 + (tz - (w0 * iw1 - w1 * iw0)) * (1.f / I2) * dt;
    float nvx = vx + a0 * dt, nvy = vy + a1 * dt, nvz = vz + a2 * dt;
    float npx = b->p[0][l] + nvx * dt, npy = b->p[1][l] + nvy * dt, npz = b->p[2][l] + nvz * dt;
    float nqw = qw + (-qx * n0 - qy * n1 - qz * n2) * h, nqx = qx + (qw * n0 + qy * n2 - qz * n1) * h;
    float nqy = qy + (qw * n1 - qx * n2 + qz * n0) * h, nqz = qz + (qw * n2 + qx * n1 - qy * n0) * h;
    const float inv = 1.f / sqrtf(nqw * nqw + nqx * nqx + nqy * nqy + nqz * nqz);
    nqw *= inv; nqx *= inv; nqy *= inv; nqz *= inv;
    /* floor: rest on it (held level), crash on a fast impact */
    const int below = npz < zrest, impact_now = below & (nvz < -impact);
    const float yq = 1.f / sqrtf(MAXF(nqw * nqw + nqz * nqz, 1e-12f));
    npz = below ? zrest : npz;
    nvx = below ? 0.f : nvx; nvy = below ? 0.f : nvy; nvz = below ? 0.f : nvz;
    nqw = below ? nqw * yq : nqw; nqx = below ? 0.f : nqx; nqy = below ? 0.f : nqy; nqz = below ? nqz * yq : nqz;
    const int keep_om = live && !below;
    b->op[0][l] = live ? w0 : b->op[0][l]; b->op[1][l] = live ? w1 : b->op[1][l]; b->op[2][l] = live ? w2 : b->op[2][l];
    b->om[0][l] = keep_om ? n0 : 0.f; b->om[1][l] = keep_om ? n1 : 0.f; b->om[2][l] = keep_om ? n2 : 0.f;
    b->pi[0][l] = live ? i0 : b->pi[0][l]; b->pi[1][l] = live ? i1 : b->pi[1][l]; b->pi[2][l] = live ? i2 : b->pi[2][l];
    b->q[0][l] = live ? nqw : qw; b->q[1][l] = live ? nqx : qx; b->q[2][l] = live ? nqy : qy; b->q[3][l] = live ? nqz : qz;
    const float t = b->t[l] + dt;
    b->t[l] = t;
    const int low = (grace >= 0.f) & (npz < floorz) & (t > grace);
    const int ceil = (arena_on > 0.f) & (npz > az);
    const int out = (arena_on > 0.f) & ((npx < ax0) | (npx > ax1) | (npy < ay0) | (npy > ay1));
    /* the first reason in this order counts */
    const int why = (impact_now | low) ? R_FLOOR : ceil ? R_CEILING : out ? R_ARENA : R_NONE;
    /* the target gate: passed, or its plane crossed off-centre (a frame hit): cfrace.sim.gates.crossing */
    const float gc = b->gc[l], gs = b->gs[l], gx = b->gx[l], gy = b->gy[l], gz = b->gz[l];
    const float dx0 = b->p[0][l] - gx, dy0 = b->p[1][l] - gy, dx1 = npx - gx, dy1 = npy - gy;
    const float pl0 = gc * dx0 + gs * dy0, pl1 = -gs * dx0 + gc * dy0, pl2 = b->p[2][l] - gz;
    const float nl0 = gc * dx1 + gs * dy1, nl1 = -gs * dx1 + gc * dy1, nl2 = npz - gz;
    const int crossed = pl0 > 0.f && nl0 <= 0.f;
    const float frac = pl0 / MAXF(pl0 - nl0, 1e-9f);
    const float cy = fabsf(pl1 + frac * (nl1 - pl1)), cz = fabsf(pl2 + frac * (nl2 - pl2));
    b->passed[l] = crossed && nl0 * nl0 + nl1 * nl1 + nl2 * nl2 < PASS_RADIUS * PASS_RADIUS && cy < PASS_HALF && cz < PASS_HALF;
    b->hit[l] = crossed && cy < outer && cz < outer && (cy >= FRAME_HIT_HALF || cz >= FRAME_HIT_HALF);
    b->live[l] = live; b->why[l] = why; b->contact[l] = 0;
    b->np[0][l] = live ? npx : b->p[0][l]; b->np[1][l] = live ? npy : b->p[1][l]; b->np[2][l] = live ? npz : b->p[2][l];
    b->nv[0][l] = nvx; b->nv[1][l] = nvy; b->nv[2][l] = nvz;
  }
}

typedef struct { float cx, cy, cz, hx, hy, hz, c, s; } Box; /* centre, half sizes, cos and sin of the yaw */

static inline Box box_at(const float *ctr, const float *half, const float *cs, const float *sn, int k) {
  Box x = {ctr[3 * k], ctr[3 * k + 1], ctr[3 * k + 2], half[3 * k], half[3 * k + 1], half[3 * k + 2], cs[k], sn[k]};
  return x;
}

/* world position -> box frame */
static inline void to_box(const Box *x, float px, float py, float pz, float *l0, float *l1, float *l2) {
  const float dx = px - x->cx, dy = py - x->cy;
  *l0 = x->c * dx + x->s * dy;
  *l1 = -x->s * dx + x->c * dy;
  *l2 = pz - x->cz;
}

/* squared distance from a point to the box (0 inside) */
static inline float box_excess2(const Box *x, float px, float py, float pz) {
  float l0, l1, l2;
  to_box(x, px, py, pz, &l0, &l1, &l2);
  const float e0 = MAXF(fabsf(l0) - x->hx, 0.f), e1 = MAXF(fabsf(l1) - x->hy, 0.f), e2 = MAXF(fabsf(l2) - x->hz, 0.f);
  return e0 * e0 + e1 * e1 + e2 * e2;
}

/* any frame bar of any gate: a drone can only touch a bar within `reach` of its gate's centre */
static void bars(Block *restrict b, const Setup *S, float reach2, float r2) {
  for (int u = 0; u < S->nug; u++) {
    const int g = S->ug[u];
    const float gx = S->gates[4 * g], gy = S->gates[4 * g + 1], gz = S->gates[4 * g + 2];
    int any = 0;
#pragma omp simd reduction(|:any)
    for (int l = 0; l < NB; l++) {
      const float ex = b->np[0][l] - gx, ey = b->np[1][l] - gy, ez = b->np[2][l] - gz;
      b->near[l] = !(ex * ex + ey * ey + ez * ez > reach2);
      any |= b->near[l];
    }
    if (!any) continue; /* a shortcut only: lanes not near cannot hit */
    for (int k = 4 * g; k < 4 * g + 4; k++) {
      const Box x = box_at(S->bar_c, S->bar_h, S->bar_cos, S->bar_sin, k);
      SIMD
      for (int l = 0; l < NB; l++) {
        b->hit[l] |= b->near[l] & (box_excess2(&x, b->np[0][l], b->np[1][l], b->np[2][l]) < r2);
      }
    }
  }
}

/* obstacles: touching is a contact; inside the push-out distance, push out to the surface and
 * remove the velocity into the box */
static void obstacles(Block *restrict b, const Setup *S, float radius, float r2, float rc2) {
  for (int k = 0; k < S->K; k++) {
    const Box x = box_at(S->ob_c, S->ob_h, S->ob_cos, S->ob_sin, k);
    const float cx = x.cx, cy = x.cy, cz = x.cz, hx = x.hx, hy = x.hy, hz = x.hz, c = x.c, s = x.s;
    int any = 0;
#pragma omp simd reduction(|:any)
    for (int l = 0; l < NB; l++) {
      const float d2 = box_excess2(&x, b->np[0][l], b->np[1][l], b->np[2][l]);
      b->contact[l] |= b->live[l] & (d2 < rc2);
      any |= b->live[l] & (d2 < r2);
    }
    if (!any) continue; /* a shortcut only: no lane to push out */
    SIMD
    for (int l = 0; l < NB; l++) {
      float l0, l1, l2;
      to_box(&x, b->np[0][l], b->np[1][l], b->np[2][l], &l0, &l1, &l2);
      const float c0 = CLAMP(l0, -hx, hx), c1 = CLAMP(l1, -hy, hy), c2 = CLAMP(l2, -hz, hz);
      const float f0 = l0 - c0, f1 = l1 - c1, f2 = l2 - c2;
      const float d2 = f0 * f0 + f1 * f1 + f2 * f2;
      const int hit = b->live[l] & (d2 < r2);
      const float dist = sqrtf(d2), inv = 1.f / MAXF(dist, 1e-9f);
      /* inside the box: leave along the axis of least penetration */
      const float p0 = hx - fabsf(l0), p1 = hy - fabsf(l1), p2 = hz - fabsf(l2);
      const int ax1 = p1 < p0, ax2 = p2 < (ax1 ? p1 : p0);
      const int outside = dist > 1e-9f;
      const float n0 = outside ? f0 * inv : ((!ax1 && !ax2) ? (l0 >= 0.f ? 1.f : -1.f) : 0.f);
      const float n1 = outside ? f1 * inv : ((ax1 && !ax2) ? (l1 >= 0.f ? 1.f : -1.f) : 0.f);
      const float n2 = outside ? f2 * inv : (ax2 ? (l2 >= 0.f ? 1.f : -1.f) : 0.f);
      const float m0 = c0 + n0 * radius, m1 = c1 + n1 * radius, m2 = c2 + n2 * radius;
      b->np[0][l] = hit ? c * m0 - s * m1 + cx : b->np[0][l];
      b->np[1][l] = hit ? s * m0 + c * m1 + cy : b->np[1][l];
      b->np[2][l] = hit ? m2 + cz : b->np[2][l];
      const float nw0 = c * n0 - s * n1, nw1 = s * n0 + c * n1, nw2 = n2;
      const float vn = b->nv[0][l] * nw0 + b->nv[1][l] * nw1 + b->nv[2][l] * nw2;
      const int into = hit && vn < 0.f;
      b->nv[0][l] = into ? b->nv[0][l] - vn * nw0 : b->nv[0][l];
      b->nv[1][l] = into ? b->nv[1][l] - vn * nw1 : b->nv[1][l];
      b->nv[2][l] = into ? b->nv[2][l] - vn * nw2 : b->nv[2][l];
    }
  }
}

/* drone-drone contacts among the drones of one world not crashed before this step (simultaneous) */
static void drones(Block *restrict b, const Setup *S, float radius, float rc) {
  const int DW = S->D * S->WB; /* lanes of whole worlds; the partner k drones on is k * WB lanes on, cyclically */
  const float near2 = (2.f * rc + 1e-3f) * (2.f * rc + 1e-3f);
  SIMD
  for (int l = 0; l < NB; l++) {
    for (int a = 0; a < 3; a++) b->rp[a][l] = b->np[a][l];
    b->rlive[l] = b->live[l];
  }
  SIMD /* after the loop above: with NB % D != 0 this overwrites its last lanes */
  for (int l = 0; l < NB; l++) {
    for (int a = 0; a < 3; a++) b->rp[a][l + DW] = b->np[a][l];
    b->rlive[l + DW] = b->live[l];
  }
  int any = 0;
  for (int k = 1; k < S->D; k++) {
    const int s = k * S->WB;
#pragma omp simd reduction(|:any)
    for (int l = 0; l < NB; l++) {
      const int o = l + s;
      const float d0 = b->np[0][l] - b->rp[0][o], d1 = b->np[1][l] - b->rp[1][o], d2 = b->np[2][l] - b->rp[2][o];
      any |= b->live[l] & b->rlive[o] & (d0 * d0 + d1 * d1 + d2 * d2 < near2);
    }
  }
  if (!any) return; /* a shortcut only: no two drones near enough to touch */
  SIMD
  for (int l = 0; l < NB; l++)
    for (int a = 0; a < 3; a++) { b->dp[a][l] = 0.f; b->dv[a][l] = 0.f; b->rv[a][l] = b->nv[a][l]; }
  SIMD
  for (int l = 0; l < NB; l++)
    for (int a = 0; a < 3; a++) b->rv[a][l + DW] = b->nv[a][l];
  for (int k = 1; k < S->D; k++) {
    const int s = k * S->WB;
    SIMD
    for (int l = 0; l < NB; l++) {
      const int o = l + s, pair = b->live[l] & b->rlive[o];
      const float d0 = b->np[0][l] - b->rp[0][o], d1 = b->np[1][l] - b->rp[1][o], d2 = b->np[2][l] - b->rp[2][o];
      const float dist = sqrtf(d0 * d0 + d1 * d1 + d2 * d2);
      b->contact[l] |= pair & (dist < 2.f * rc);
      const int touch = pair & (dist < 2.f * radius);
      const float inv_d = 1.f / MAXF(dist, 1e-6f), depth = touch ? 2.f * radius - dist : 0.f;
      const float e0 = d0 * inv_d, e1 = d1 * inv_d, e2 = d2 * inv_d;
      const float rv = (b->nv[0][l] - b->rv[0][o]) * e0 + (b->nv[1][l] - b->rv[1][o]) * e1
                       + (b->nv[2][l] - b->rv[2][o]) * e2;
      const float cv = (touch & (rv < 0.f)) ? rv : 0.f;
      b->dp[0][l] += depth * e0; b->dp[1][l] += depth * e1; b->dp[2][l] += depth * e2;
      b->dv[0][l] += cv * e0; b->dv[1][l] += cv * e1; b->dv[2][l] += cv * e2;
    }
  }
  SIMD
  for (int l = 0; l < NB; l++)
    for (int a = 0; a < 3; a++) { b->np[a][l] += 0.5f * b->dp[a][l]; b->nv[a][l] -= 0.5f * b->dv[a][l]; }
}

/* contact time, crash bookkeeping, race progress */
static void progress(Block *restrict b, const Setup *S) {
  const float dt = S->cst[C_DT], longc = S->cst[C_LONGC];
  const int G = S->G;
  int any_pass = 0;
#pragma omp simd reduction(|:any_pass)
  for (int l = 0; l < NB; l++) {
    const int live = b->live[l], contact = live & b->contact[l], early = b->why[l] != R_NONE;
    const float ct = contact ? b->ct[l] + dt : 0.f;
    b->ct[l] = ct;
    const int longc_now = live & (ct > longc);
    /* the first reason counts: floor/ceiling/arena, then a gate frame, then long contact */
    const int crash = live & (early | b->hit[l] | longc_now);
    const int why = early ? b->why[l] : b->hit[l] ? R_GATE : R_CONTACT;
    for (int a = 0; a < 3; a++) {
      b->p[a][l] = b->np[a][l];
      b->v[a][l] = live ? b->nv[a][l] : 0.f;
    }
    for (int r = 0; r < 4; r++) b->mo[r][l] = crash ? 0.f : b->mo[r][l];
    b->crashed[l] |= crash;
    b->reason[l] = crash ? why : b->reason[l];
    b->ev_c[l] |= crash;
    b->ev_ct[l] |= contact;
    const int passed = live & (crash ^ 1) & b->passed[l];
    const int nt = b->tgt[l] + 1, ng = b->gpm[l] + 1;
    b->tgt[l] = passed ? (nt == G ? 0 : nt) : b->tgt[l];
    b->gpm[l] = passed ? (ng == G ? 0 : ng) : b->gpm[l];
    any_pass |= passed;
    const int lap = passed & (ng == G);
    b->ev_g[l] += passed;
    b->ev_l[l] += lap;
    const float t = b->t[l];
    b->lap_last[l] = lap ? t - b->lap_start[l] : b->lap_last[l];
    b->lap_start[l] = lap ? t : b->lap_start[l];
  }
  if (any_pass) target_poses(b, S);
}

int cfrace_step(int W, int D, int G, int B, int K, int substeps, int nthreads, void *const *P) {
  if (D < 1 || D > MAXD) return -1;
  if (G < 1 || G > MAXG || B != 4 * G) return -2;
  Setup S;
  S.D = D; S.G = G; S.K = K;
  S.cst = P[P_CST]; S.gates = P[P_GATES];
  S.bar_c = P[P_BAR_C]; S.bar_h = P[P_BAR_H]; S.bar_cos = P[P_BAR_COS]; S.bar_sin = P[P_BAR_SIN];
  S.ob_c = P[P_OB_C]; S.ob_h = P[P_OB_H]; S.ob_cos = P[P_OB_COS]; S.ob_sin = P[P_OB_SIN];
  S.nug = 0;
  for (int g = 0; g < G; g++) {
    S.gcos[g] = cosf(S.gates[4 * g + 3]);
    S.gsin[g] = sinf(S.gates[4 * g + 3]);
    int dup = 0;
    for (int u = 0; u < S.nug && !dup; u++) dup = !memcmp(S.gates + 4 * g, S.gates + 4 * S.ug[u], 4 * sizeof(float));
    if (!dup) S.ug[S.nug++] = g;
  }
  const float radius = S.cst[C_RADIUS], outer = S.cst[C_OUTER];
  /* a bar can only be touched within this distance of its gate centre */
  const float reach = outer * 1.41421356f + radius + 0.05f, reach2 = reach * reach, r2 = radius * radius;
  /* touching (contact) extends 1 mm beyond the push-out distance, so resting against a wall is contact */
  const float rc = radius + 1e-3f, rc2 = rc * rc;
  const int wpb = S.WB = NB / D, nblocks = (W + wpb - 1) / wpb;
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int blk = 0; blk < nblocks; blk++) {
    const int w0 = blk * wpb, nw = MINF(wpb, W - w0);
    Block b;
    gather(&b, P, &S, w0, nw);
    for (int sub = 0; sub < substeps; sub++) {
      physics(&b, &S);
      bars(&b, &S, reach2, r2);
      obstacles(&b, &S, radius, r2, rc2);
      if (D > 1) drones(&b, &S, radius, rc);
      progress(&b, &S);
    }
    scatter(&b, P, &S, w0, nw);
  }
  return 0;
}
