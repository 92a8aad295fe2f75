/* cfrace fused CPU kernel: the same model as cfrace/sim/simulator.py::_substep (the torch
 * reference), one loop per world over substeps and drones, so that everything a drone does in
 * 2 ms stays in registers. Built at first use by cfrace/sim/ckernel.py with the system C compiler;
 * the torch path is the fallback and the reference the tests compare against.
 * Layouts: all arrays contiguous, row-major, shapes as in simulator.py (W worlds, D drones). */
#include <math.h>
#include <stdint.h>
#include <string.h>

enum { R_NONE = 0, R_FLOOR = 1, R_CEILING = 2, R_ARENA = 3, R_GATE = 4, R_CONTACT = 5 };
#define MAXD 16
/* plain compares: one min/max instruction each (fminf/fmaxf carry NaN rules that cost a call) */
#define MINF(a, b) ((a) < (b) ? (a) : (b))
#define MAXF(a, b) ((a) > (b) ? (a) : (b))

/* constants: indices into cst[] (filled by ckernel.py, keep in sync) */
enum {
  C_DT, C_MASS, C_IX, C_IY, C_IZ, C_KETA, C_KRATIO, C_RX0, C_RX1, C_RX2, C_RX3, C_RY0, C_RY1, C_RY2, C_RY3,
  C_DIR0, C_DIR1, C_DIR2, C_DIR3, C_MIX0, /* 16 values */ C_WMIN = C_MIX0 + 16, C_WMAX, C_IL0, C_IL1, C_IL2,
  C_G, C_RADIUS, C_ZREST, C_AX0, C_AX1, C_AY0, C_AY1, C_AZ, C_OUTER, C_GRACE, C_FLOORZ, C_IMPACT, C_LONGC,
  C_ARENA_ON, C_COUNT
};

static inline void to_gate(const float *gate, float c, float s, const float *p, float *out) {
  float dx = p[0] - gate[0], dy = p[1] - gate[1], dz = p[2] - gate[2];
  out[0] = c * dx + s * dy;
  out[1] = -s * dx + c * dy;
  out[2] = dz;
}

static inline float box_dist2(const float *p, const float *ctr, const float *half, float c, float s) {
  float dx = p[0] - ctr[0], dy = p[1] - ctr[1], dz = p[2] - ctr[2];
  float l[3] = {c * dx + s * dy, -s * dx + c * dy, dz};
  float acc = 0.f;
  for (int k = 0; k < 3; k++) {
    float e = fabsf(l[k]) - half[k];
    if (e > 0.f) acc += e * e;
  }
  return acc;
}

int cfrace_step(int W, int D, int G, int B, int K, int substeps, int nthreads, const float *cst,
                float *pos, float *vel, float *quat, float *omega, float *motor, float *pid_int, float *omega_prev,
                int64_t *target, int64_t *gates_passed, int64_t *laps, float *lap_start, float *lap_last,
                uint8_t *crashed, int64_t *reason, float *contact_time, float *time,
                const float *kp, const float *ki, const float *kd, const float *k_aero, const float *alpha,
                const float *gates, const float *bar_c, const float *bar_h, const float *bar_cos, const float *bar_sin,
                const float *ob_c, const float *ob_h, const float *ob_cos, const float *ob_sin,
                const float *thrust_cmd, const float *rates_cmd,
                int64_t *ev_gates, int64_t *ev_laps, uint8_t *ev_crashed, uint8_t *ev_contact, int64_t *ev_reason) {
  if (D > MAXD) return -1;
  float cs[C_COUNT];
  memcpy(cs, cst, sizeof(cs));
  const float inv_keta = (float)(1.0 / (double)cs[C_KETA]);
  const float dt = cs[C_DT], inv_dt = (float)(1.0 / (double)cs[C_DT]), inv_m = (float)(1.0 / (double)cs[C_MASS]);
  const float I[3] = {cs[C_IX], cs[C_IY], cs[C_IZ]};
  const float invI[3] = {1.f / cs[C_IX], 1.f / cs[C_IY], 1.f / cs[C_IZ]};
  const float il[3] = {cs[C_IL0], cs[C_IL1], cs[C_IL2]};
  const float radius = cs[C_RADIUS], zrest = cs[C_ZREST], outer = cs[C_OUTER];
  if (G > 256 || B != 4 * G) return -2;
  float gcos[256], gsin[256];
  for (int g = 0; g < G; g++) { gcos[g] = cosf(gates[4 * g + 3]); gsin[g] = sinf(gates[4 * g + 3]); }
  /* a bar can only be touched within this distance of its gate centre */
  const float reach = outer * 1.41421356f + radius + 0.05f, reach2 = reach * reach, r2 = radius * radius;
  /* touching (contact) extends 1 mm beyond the push-out distance, so resting against a wall is contact */
  const float rc = radius + 1e-3f, rc2 = rc * rc;
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int w = 0; w < W; w++) {
    for (int i = 0; i < D; i++) {
      int64_t n = (int64_t)w * D + i;
      ev_gates[n] = 0; ev_laps[n] = 0; ev_crashed[n] = 0; ev_contact[n] = 0;
    }
    for (int sub = 0; sub < substeps; sub++) {
      float t = time[w] + dt;
      uint8_t was_crashed[MAXD], crash[MAXD], contact[MAXD], passed[MAXD];
      int64_t why[MAXD];
      float npos[MAXD][3], nvel[MAXD][3];
      for (int i = 0; i < D; i++) {
        int64_t n = (int64_t)w * D + i;
        float *p = pos + 3 * n, *v = vel + 3 * n, *q = quat + 4 * n, *om = omega + 3 * n, *mo = motor + 4 * n;
        float *pi = pid_int + 3 * n, *op = omega_prev + 3 * n;
        was_crashed[i] = crashed[n];
        crash[i] = 0; contact[i] = 0; passed[i] = 0; why[i] = R_NONE;
        memcpy(npos[i], p, sizeof(float) * 3);
        memcpy(nvel[i], v, sizeof(float) * 3);
        if (was_crashed[i]) continue;
        /* body-rate PID, derivative on the measured rate */
        float tau_des[3];
        for (int k = 0; k < 3; k++) {
          float err = rates_cmd[3 * n + k] - om[k];
          float ii = pi[k] + err * dt;
          ii = MINF(MAXF(ii, -il[k]), il[k]);
          pi[k] = ii;
          float dm = (om[k] - op[k]) * inv_dt;
          tau_des[k] = I[k] * (kp[3 * n + k] * err + ki[3 * n + k] * ii - kd[3 * n + k] * dm);
        }
        /* mixer and motors */
        float wr[4] = {thrust_cmd[n], tau_des[0], tau_des[1], tau_des[2]};
        float f[4], msum = 0.f;
        for (int r = 0; r < 4; r++) {
          const float *m = cst + C_MIX0 + 4 * r;
          float fd = wr[0] * m[0] + wr[1] * m[1] + wr[2] * m[2] + wr[3] * m[3];
          float wd = sqrtf(MAXF(fd, 0.f) * inv_keta);
          wd = MINF(MAXF(wd, cs[C_WMIN]), cs[C_WMAX]);
          mo[r] = mo[r] + (wd - mo[r]) * alpha[n];
          f[r] = cs[C_KETA] * mo[r] * mo[r];
          msum += mo[r];
        }
        float fz = f[0] + f[1] + f[2] + f[3];
        float tau[3] = {
            f[0] * cs[C_RY0] + f[1] * cs[C_RY1] + f[2] * cs[C_RY2] + f[3] * cs[C_RY3],
            -(f[0] * cs[C_RX0] + f[1] * cs[C_RX1] + f[2] * cs[C_RX2] + f[3] * cs[C_RX3]),
            cs[C_KRATIO] * (f[0] * cs[C_DIR0] + f[1] * cs[C_DIR1] + f[2] * cs[C_DIR2] + f[3] * cs[C_DIR3])};
        /* rotation from the current attitude */
        float qw = q[0], qx = q[1], qy = q[2], qz = q[3];
        float R[9] = {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
                      2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
                      2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)};
        float vb[3], fb[3], acc[3];
        for (int k = 0; k < 3; k++) vb[k] = R[k] * v[0] + R[3 + k] * v[1] + R[6 + k] * v[2];
        for (int k = 0; k < 3; k++) fb[k] = -msum * k_aero[3 * n + k] * vb[k];
        fb[2] += fz;
        for (int k = 0; k < 3; k++) acc[k] = (R[3 * k] * fb[0] + R[3 * k + 1] * fb[1] + R[3 * k + 2] * fb[2]) * inv_m;
        acc[2] -= cs[C_G];
        /* Euler's equation */
        float iw[3] = {I[0] * om[0], I[1] * om[1], I[2] * om[2]};
        float gyro[3] = {om[1] * iw[2] - om[2] * iw[1], om[2] * iw[0] - om[0] * iw[2], om[0] * iw[1] - om[1] * iw[0]};
        float nom[3];
        for (int k = 0; k < 3; k++) {
          nvel[i][k] = v[k] + acc[k] * dt;
          npos[i][k] = p[k] + nvel[i][k] * dt;
          nom[k] = om[k] + (tau[k] - gyro[k]) * invI[k] * dt;
        }
        float ox = nom[0], oy = nom[1], oz = nom[2], h = 0.5f * dt;
        float nq[4] = {qw + (-qx * ox - qy * oy - qz * oz) * h, qx + (qw * ox + qy * oz - qz * oy) * h,
                       qy + (qw * oy - qx * oz + qz * ox) * h, qz + (qw * oz + qx * oy - qy * ox) * h};
        float inv = 1.f / sqrtf(nq[0] * nq[0] + nq[1] * nq[1] + nq[2] * nq[2] + nq[3] * nq[3]);
        for (int k = 0; k < 4; k++) nq[k] *= inv;
        memcpy(op, om, sizeof(float) * 3);
        memcpy(om, nom, sizeof(float) * 3);
        /* floor */
        int below = npos[i][2] < zrest;
        if (below && nvel[i][2] < -cs[C_IMPACT]) { crash[i] = 1; why[i] = R_FLOOR; }
        if (below) {
          npos[i][2] = zrest;
          nvel[i][0] = nvel[i][1] = nvel[i][2] = 0.f;
          om[0] = om[1] = om[2] = 0.f;
          float yq = 1.f / sqrtf(MAXF(nq[0] * nq[0] + nq[3] * nq[3], 1e-12f));
          nq[0] *= yq; nq[1] = 0.f; nq[2] = 0.f; nq[3] *= yq;
        }
        memcpy(q, nq, sizeof(float) * 4);
        if (cs[C_GRACE] >= 0.f && npos[i][2] < cs[C_FLOORZ] && t > cs[C_GRACE]) {
          if (!crash[i]) why[i] = R_FLOOR;
          crash[i] = 1;
        }
        if (cs[C_ARENA_ON] > 0.f) {
          if (npos[i][2] > cs[C_AZ] && !crash[i]) { crash[i] = 1; why[i] = R_CEILING; }
          int out = npos[i][0] < cs[C_AX0] || npos[i][0] > cs[C_AX1] || npos[i][1] < cs[C_AY0] || npos[i][1] > cs[C_AY1];
          if (out && !crash[i]) { crash[i] = 1; why[i] = R_ARENA; }
        }
        /* target gate: pass or plane hit; any frame bar */
        const int64_t tg = target[n];
        const float *gate = gates + 4 * tg;
        float pl[3], nl[3];
        to_gate(gate, gcos[tg], gsin[tg], p, pl);
        to_gate(gate, gcos[tg], gsin[tg], npos[i], nl);
        int hit = 0;
        if (pl[0] > 0.f && nl[0] <= 0.f) {
          float frac = pl[0] / MAXF(pl[0] - nl[0], 1e-9f);
          float ay = fabsf(pl[1] + frac * (nl[1] - pl[1])), az = fabsf(pl[2] + frac * (nl[2] - pl[2]));
          float dist = sqrtf(nl[0] * nl[0] + nl[1] * nl[1] + nl[2] * nl[2]);
          passed[i] = dist < 1.0f && ay < 0.5f && az < 0.5f;
          hit = ay < outer && az < outer && (ay >= 0.4f || az >= 0.4f);
        }
        for (int g = 0; g < G && !hit; g++) {
          float ex = npos[i][0] - gates[4 * g], ey = npos[i][1] - gates[4 * g + 1], ez = npos[i][2] - gates[4 * g + 2];
          if (ex * ex + ey * ey + ez * ez > reach2) continue;
          for (int b = 4 * g; b < 4 * g + 4 && !hit; b++)
            if (box_dist2(npos[i], bar_c + 3 * b, bar_h + 3 * b, bar_cos[b], bar_sin[b]) < r2) hit = 1;
        }
        if (hit && !crash[i]) { crash[i] = 1; why[i] = R_GATE; }
        /* obstacles: push out, remove the velocity into the box */
        for (int k = 0; k < K; k++) {
          const float *ctr = ob_c + 3 * k, *hh = ob_h + 3 * k;
          float c = ob_cos[k], s = ob_sin[k];
          float dx = npos[i][0] - ctr[0], dy = npos[i][1] - ctr[1], dz = npos[i][2] - ctr[2];
          float l[3] = {c * dx + s * dy, -s * dx + c * dy, dz}, cl[3], df[3], nloc[3];
          float d2 = 0.f;
          for (int a = 0; a < 3; a++) {
            cl[a] = MINF(MAXF(l[a], -hh[a]), hh[a]);
            df[a] = l[a] - cl[a];
            d2 += df[a] * df[a];
          }
          if (!(d2 < rc2)) continue;
          contact[i] = 1;
          if (!(d2 < r2)) continue;
          float dist = sqrtf(d2);
          if (dist > 1e-9f) {
            for (int a = 0; a < 3; a++) nloc[a] = df[a] / dist;
          } else {
            int am = 0;
            float best = hh[0] - fabsf(l[0]);
            for (int a = 1; a < 3; a++) if (hh[a] - fabsf(l[a]) < best) { best = hh[a] - fabsf(l[a]); am = a; }
            for (int a = 0; a < 3; a++) nloc[a] = a == am ? (l[a] >= 0.f ? 1.f : -1.f) : 0.f;
          }
          for (int a = 0; a < 3; a++) l[a] = cl[a] + nloc[a] * radius;
          npos[i][0] = c * l[0] - s * l[1] + ctr[0];
          npos[i][1] = s * l[0] + c * l[1] + ctr[1];
          npos[i][2] = l[2] + ctr[2];
          float nw[3] = {c * nloc[0] - s * nloc[1], s * nloc[0] + c * nloc[1], nloc[2]};
          float vn = nvel[i][0] * nw[0] + nvel[i][1] * nw[1] + nvel[i][2] * nw[2];
          if (vn < 0.f) for (int a = 0; a < 3; a++) nvel[i][a] -= vn * nw[a];
        }
      }
      /* drone-drone contacts among drones not crashed before this step (simultaneous) */
      if (D > 1) {
        float dp[MAXD][3], dv[MAXD][3];
        memset(dp, 0, sizeof(dp)); memset(dv, 0, sizeof(dv));
        for (int i = 0; i < D; i++) {
          if (was_crashed[i]) continue;
          for (int j = 0; j < D; j++) {
            if (j == i || was_crashed[j]) continue;
            float d[3] = {npos[i][0] - npos[j][0], npos[i][1] - npos[j][1], npos[i][2] - npos[j][2]};
            float dist = sqrtf(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            if (!(dist < 2.f * rc)) continue;
            contact[i] = 1;
            float inv_d = 1.f / MAXF(dist, 1e-6f), depth = MAXF(2.f * radius - dist, 0.f);
            float nrm[3] = {d[0] * inv_d, d[1] * inv_d, d[2] * inv_d};
            float rv = (nvel[i][0] - nvel[j][0]) * nrm[0] + (nvel[i][1] - nvel[j][1]) * nrm[1] + (nvel[i][2] - nvel[j][2]) * nrm[2];
            for (int a = 0; a < 3; a++) {
              dp[i][a] += depth * nrm[a];
              if (rv < 0.f) dv[i][a] += rv * nrm[a];
            }
          }
        }
        for (int i = 0; i < D; i++)
          for (int a = 0; a < 3; a++) { npos[i][a] += 0.5f * dp[i][a]; nvel[i][a] -= 0.5f * dv[i][a]; }
      }
      /* contacts, crash bookkeeping, race progress */
      for (int i = 0; i < D; i++) {
        int64_t n = (int64_t)w * D + i;
        if (was_crashed[i]) {
          float *v = vel + 3 * n, *om = omega + 3 * n, *mo = motor + 4 * n;
          v[0] = v[1] = v[2] = 0.f; om[0] = om[1] = om[2] = 0.f;
          mo[0] = mo[1] = mo[2] = mo[3] = 0.f;
          contact_time[n] = 0.f;
          continue;
        }
        contact_time[n] = contact[i] ? contact_time[n] + dt : 0.f;
        if (contact_time[n] > cs[C_LONGC] && !crash[i]) { crash[i] = 1; why[i] = R_CONTACT; }
        memcpy(pos + 3 * n, npos[i], sizeof(float) * 3);
        memcpy(vel + 3 * n, nvel[i], sizeof(float) * 3);
        if (crash[i]) {
          float *mo = motor + 4 * n;
          mo[0] = mo[1] = mo[2] = mo[3] = 0.f;
          crashed[n] = 1;
          reason[n] = why[i];
          ev_crashed[n] = 1;
          passed[i] = 0;
        }
        if (contact[i]) ev_contact[n] = 1;
        if (passed[i]) {
          gates_passed[n] += 1;
          target[n] = (target[n] + 1) % G;
          ev_gates[n] += 1;
          if (gates_passed[n] % G == 0) {
            laps[n] += 1;
            ev_laps[n] += 1;
            lap_last[n] = t - lap_start[n];
            lap_start[n] = t;
          }
        }
      }
      time[w] = t;
    }
    for (int i = 0; i < D; i++) {
      int64_t n = (int64_t)w * D + i;
      ev_reason[n] = ev_crashed[n] ? reason[n] : 0;
    }
  }
  return 0;
}
