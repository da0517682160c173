/* The snake's anisotropic floor friction on any ground: MuJoCo's step with each ground contact's
 * friction frame turned about its normal so that its first tangent lies along the link's capsule axis
 * (as MuJoCo's capsule-plane collider sets it; every other collider takes the frame from the normal
 * alone, MuJoCo issue #67), before the constraints are built from it.
 *
 * Built on first use by snakeloco.sim.physics.ground_contact (a C compiler and the headers of the
 * installed mujoco wheel) and called through ctypes, which releases the GIL: a rollout here runs in
 * parallel with Python as MuJoCo's own rollout does. The Python module has the same step in numpy for
 * machines without a compiler, and the tests compare the two.
 */
#include <math.h>
#include <mujoco/mujoco.h>

/* Turn the frames of the contacts that touch a ground geom (ground[g] != 0); returns how many. */
int snakeloco_realign(const mjModel* m, mjData* d, const unsigned char* ground) {
  int changed = 0;
  for (int i = 0; i < d->ncon; i++) {
    mjContact* c = d->contact + i;
    int g1 = c->geom[0], g2 = c->geom[1], link;
    if (g1 >= 0 && ground[g1]) {
      link = g2;
    } else if (g2 >= 0 && ground[g2]) {
      link = g1;
    } else {
      continue;
    }
    if (link < 0) continue;
    const mjtNum* x = d->geom_xmat + 9 * link;
    mjtNum axis[3] = {x[2], x[5], x[8]}; /* a capsule's axis: its frame's z column */
    mjtNum* n = c->frame;
    mjtNum dot = axis[0] * n[0] + axis[1] * n[1] + axis[2] * n[2];
    mjtNum along[3] = {axis[0] - dot * n[0], axis[1] - dot * n[1], axis[2] - dot * n[2]};
    mjtNum norm = sqrt(along[0] * along[0] + along[1] * along[1] + along[2] * along[2]);
    if (norm <= 1e-9) continue; /* a link standing on its end keeps its frame */
    for (int k = 0; k < 3; k++) along[k] /= norm;
    c->frame[3] = along[0];
    c->frame[4] = along[1];
    c->frame[5] = along[2];
    c->frame[6] = n[1] * along[2] - n[2] * along[1];
    c->frame[7] = n[2] * along[0] - n[0] * along[2];
    c->frame[8] = n[0] * along[1] - n[1] * along[0];
    changed++;
  }
  return changed;
}

/* mj_step (implicit integrators) with the ground contacts re-aligned before the constraints. */
void snakeloco_step(const mjModel* m, mjData* d, const unsigned char* ground) {
  mj_checkPos(m, d);
  mj_checkVel(m, d);
  mj_fwdPosition(m, d);
  if (snakeloco_realign(m, d, ground)) {
    mj_makeConstraint(m, d);
    mj_island(m, d);
    mj_projectConstraint(m, d);
  }
  mj_sensorPos(m, d); /* mj_forwardSkip past the position stage skips its sensors */
  if (mjENABLED(mjENBL_ENERGY)) mj_energyPos(m, d);
  mj_forwardSkip(m, d, mjSTAGE_POS, 0);
  mj_checkAcc(m, d);
  mj_implicit(m, d);
}

static int any_warning(const mjData* d) {
  for (int i = 0; i < mjNWARNING; i++) {
    if (d->warning[i].number) return 1;
  }
  return 0;
}

/* One row as mujoco.rollout rolls it out (control_spec mjSTATE_CTRL, states mjSTATE_FULLPHYSICS):
 * from state0 and warmstart0, nstep steps of control (nstep x nu) into state (nstep x nstate) and
 * sensordata (nstep x nsensordata); after a warning the remaining steps repeat the current ones. */
void snakeloco_rollout(const mjModel* m, mjData* d, const unsigned char* ground, int nstep,
                       const mjtNum* state0, const mjtNum* warmstart0, const mjtNum* control,
                       mjtNum* state, mjtNum* sensordata) {
  int nstate = mj_stateSize(m, mjSTATE_FULLPHYSICS);
  int nu = m->nu, ns = m->nsensordata;
  mju_zero(d->qfrc_applied, m->nv);
  mju_zero(d->xfrc_applied, 6 * m->nbody);
  for (int i = 0; i < m->nbody; i++) {
    int id = m->body_mocapid[i];
    if (id >= 0) {
      mju_copy3(d->mocap_pos + 3 * id, m->body_pos + 3 * i);
      mju_copy4(d->mocap_quat + 4 * id, m->body_quat + 4 * i);
    }
  }
  for (int i = 0; i < m->neq; i++) d->eq_active[i] = m->eq_active0[i];
  mj_setState(m, d, state0, mjSTATE_FULLPHYSICS);
  mju_copy(d->qacc_warmstart, warmstart0, m->nv);
  for (int i = 0; i < mjNWARNING; i++) d->warning[i].number = 0;
  for (int t = 0; t < nstep; t++) {
    if (!any_warning(d)) {
      mju_copy(d->ctrl, control + (long)t * nu, nu);
      snakeloco_step(m, d, ground);
    }
    mj_getState(m, d, state + (long)t * nstate, mjSTATE_FULLPHYSICS);
    mju_copy(sensordata + (long)t * ns, d->sensordata, ns);
  }
}
