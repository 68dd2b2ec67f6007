"""The Warp kernels of `worlds`: each world's open-loop program and its success checks, on the device.

A world runs one program (`LIFT`: close, lift and shake; `SIX_CLOSE` / `SIX_PUSH`: six-dir's closing and one push;
`BENCH_SQUEEZE` / `BENCH_PUSH`: DexGraspBench's pre-grasp to squeeze and one push), one step at a time:
- `control` (before each `mujoco_warp.step`): servo targets, the wrist's mocap target, the hold weld and the push
  force from the world's step counter, as `protocols` builds them on the host; at a branch point it keeps a copy
  of the state (the state after exactly that many steps, which the pushes start from);
- `contact_flags` (after it): which worlds' objects touch the hand and the table, from the step's contacts;
- `events`: the world's checks at the steps the CPU backend checks them (`worlds.Schedule`), on the kinematics
  and contacts the step computed, i.e. of the state after t steps, where t counts the step calls before it.

A world's per-world parameters are columns of one float and one int array (`worlds.Layout`).
"""

import typing

import numpy as np

# program kinds, event codes and world status (int columns of `worlds.Layout`)
IDLE, LIFT, SIX_CLOSE, SIX_PUSH, BENCH_SQUEEZE, BENCH_PUSH = range(6)
REF, CHECK, FINAL, BRANCH = range(4)
RUNNING, DONE, BRANCHED = range(3)
HAND, OBJECT, TABLE = 1, 2, 3  # geom classes of `contact_flags`


@typing.no_type_check  # Warp's annotations are array specs, not types
def build(max_speed: float):
    """The kernels, as a namespace (compiled by Warp on first launch and cached on disk)."""
    import warp as wp

    MAX_SPEED = wp.constant(float(max_speed))
    PI = wp.constant(float(np.pi))

    @wp.func
    def angle(a: wp.quat, b: wp.quat) -> float:
        c = wp.abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
        return 2.0 * wp.acos(wp.clamp(c, 0.0, 1.0)) * 180.0 / PI

    @wp.kernel
    def control(ip: wp.array2d(dtype=int), fp: wp.array2d(dtype=float), col: wp.array(dtype=int),
                sched: wp.array(dtype=int), fsched: wp.array(dtype=float), ev_t: wp.array(dtype=int),
                ev_code: wp.array(dtype=int), obj_body: int, hold_eq: int,
                qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float), warm: wp.array2d(dtype=float),
                ctrl: wp.array2d(dtype=float), mocap_pos: wp.array2d(dtype=wp.vec3),
                mocap_quat: wp.array2d(dtype=wp.quat), eq_active: wp.array2d(dtype=bool),
                xfrc: wp.array2d(dtype=wp.spatial_vector), snap_qpos: wp.array2d(dtype=float),
                snap_qvel: wp.array2d(dtype=float), snap_warm: wp.array2d(dtype=float)):
        w = wp.tid()
        kind = ip[w, col[0]]
        if kind == 0 or ip[w, col[4]] != 0:  # idle or finished: frozen until refilled
            for i in range(qvel.shape[1]):
                qvel[w, i] = 0.0
            xfrc[w, obj_body] = wp.spatial_vector(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            if mocap_pos.shape[1] > 1:
                mocap_pos[w, 1] = wp.vec3(0.0, 0.0, -1000.0)
            return
        t = ip[w, col[1]]
        n_close = sched[0]
        n_settle = sched[1]
        n_lift = sched[2]
        n_hold = sched[3]
        n_shake = sched[4]
        n_stage = sched[5]
        waypoints = sched[6]
        dt = fsched[0]
        height = fsched[1]
        amp = fsched[2]
        period = fsched[3]
        qs = col[5]
        qt = col[6]
        qg = col[7]
        for a in range(ctrl.shape[1]):
            s = fp[w, qs + a]
            e = fp[w, qt + a]
            c = e
            if (kind == 1 or kind == 2) and t < n_close:
                c = s + float(t + 1) / float(n_close) * (e - s)
            if kind == 4 and t < 2 * n_stage:
                g = fp[w, qg + a]
                i = t
                if t >= n_stage:
                    i = t - n_stage
                k = (wp.floor(float(i * waypoints) / float(n_stage)) + 1.0) / float(waypoints)
                if t < n_stage:
                    c = s + k * (g - s)
                else:
                    c = g + k * (e - g)
            ctrl[w, a] = c
        wpc = col[8]
        off = wp.vec3(0.0, 0.0, 0.0)
        if kind == 1:
            i = t - n_close - n_settle
            if i >= 0 and i < n_lift:
                u = float(i + 1) / float(n_lift)
                off = wp.vec3(0.0, 0.0, height * (1.0 - wp.cos(PI * u)) / 2.0)
            elif i >= n_lift and i < n_lift + n_hold:
                off = wp.vec3(0.0, 0.0, height)
            elif i >= n_lift + n_hold:
                j = wp.min(i - n_lift - n_hold, n_shake - 1)
                tt = float(j + 1) * dt
                env = wp.clamp(wp.min(tt, float(n_shake) * dt - tt) / (period / 4.0), 0.0, 1.0)
                env = env * env * (3.0 - 2.0 * env)
                off = wp.vec3(amp * wp.sin(2.0 * PI * tt / period) * env, 0.0, height)
        mocap_pos[w, 0] = wp.vec3(fp[w, wpc], fp[w, wpc + 1], fp[w, wpc + 2]) + off
        q = col[9]
        mocap_quat[w, 0] = wp.quat(fp[w, q], fp[w, q + 1], fp[w, q + 2], fp[w, q + 3])
        if mocap_pos.shape[1] > 1:  # the table's mount: at the object's table for lift-shake, else far below
            z = -1000.0
            if kind == 1:
                z = fp[w, col[22]]
            mocap_pos[w, 1] = wp.vec3(0.0, 0.0, z)
        if hold_eq >= 0:
            eq_active[w, hold_eq] = wp.where(kind == 2, True, False)
        f = wp.vec3(0.0, 0.0, 0.0)
        if kind == 3 or kind == 5:
            fc = col[10]
            f = wp.vec3(fp[w, fc], fp[w, fc + 1], fp[w, fc + 2])
        xfrc[w, obj_body] = wp.spatial_vector(f[0], f[1], f[2], 0.0, 0.0, 0.0)
        p = ip[w, col[2]]
        if p < ip[w, col[3]] and ev_t[p] == t and ev_code[p] == 3:  # a branch point: keep the state after t steps
            for i in range(qpos.shape[1]):
                snap_qpos[w, i] = qpos[w, i]
            for i in range(qvel.shape[1]):
                snap_qvel[w, i] = qvel[w, i]
                snap_warm[w, i] = warm[w, i]

    @wp.kernel
    def clear_flags(touch: wp.array(dtype=int), table: wp.array(dtype=int)):
        w = wp.tid()
        touch[w] = 0
        table[w] = 0

    @wp.kernel
    def contact_flags(nacon: wp.array(dtype=int), geom: wp.array(dtype=wp.vec2i), worldid: wp.array(dtype=int),
                      gclass: wp.array(dtype=int), touch: wp.array(dtype=int), table: wp.array(dtype=int)):
        c = wp.tid()
        if c >= nacon[0]:
            return
        g = geom[c]
        if g[0] < 0 or g[1] < 0:
            return
        a = gclass[g[0]]
        b = gclass[g[1]]
        w = worldid[c]
        if (a == 2 and b == 1) or (a == 1 and b == 2):
            touch[w] = 1
        if (a == 2 and b == 3) or (a == 3 and b == 2):
            table[w] = 1

    @wp.kernel
    def events(ip: wp.array2d(dtype=int), fp: wp.array2d(dtype=float), col: wp.array(dtype=int),
               ev_t: wp.array(dtype=int), ev_code: wp.array(dtype=int), bounds: wp.array(dtype=float),
               obj_body: int, root_body: int, bad_overflow: int, overflow: wp.array(dtype=int),
               qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float),
               xpos: wp.array2d(dtype=wp.vec3), xquat: wp.array2d(dtype=wp.quat), xmat: wp.array2d(dtype=wp.mat33),
               touch: wp.array(dtype=int), table: wp.array(dtype=int)):
        w = wp.tid()
        kind = ip[w, col[0]]
        st = col[4]
        if kind == 0 or ip[w, st] != 0:
            return
        t = ip[w, col[1]]
        if (overflow[w] & bad_overflow) != 0:
            ip[w, col[15]] = 1  # flagged: the host runs this grasp again on the CPU
            ip[w, st] = 1
            return
        bad = bool(False)
        for i in range(qpos.shape[1]):
            if not wp.isfinite(qpos[w, i]):
                bad = True
        for i in range(qvel.shape[1]):
            v = qvel[w, i]
            if not wp.isfinite(v) or wp.abs(v) > MAX_SPEED:
                bad = True
        if bad:
            ip[w, col[14]] = 1
            ip[w, st] = 1
            return
        max_slip = bounds[0]
        max_move = bounds[1]
        max_rot = bounds[2]
        pos = xpos[w, obj_body]
        quat = xquat[w, obj_body]
        rel = wp.transpose(xmat[w, root_body]) * (pos - xpos[w, root_body])
        rp = col[11]
        rq = col[12]
        rr = col[13]
        mv = col[16]
        rt = col[17]
        p = ip[w, col[2]]
        stop = ip[w, col[3]]
        while p < stop and ev_t[p] == t and ip[w, st] == 0:
            code = ev_code[p]
            ref_q = wp.quat(fp[w, rq], fp[w, rq + 1], fp[w, rq + 2], fp[w, rq + 3])
            if code == 0:  # reference pose
                for i in range(3):
                    fp[w, rp + i] = pos[i]
                    fp[w, rr + i] = rel[i]
                for i in range(4):
                    fp[w, rq + i] = quat[i]
            elif code == 3:  # branch: the pushes start from here
                for i in range(3):
                    fp[w, rp + i] = pos[i]
                for i in range(4):
                    fp[w, rq + i] = quat[i]
                ip[w, col[18]] = touch[w]
                ip[w, st] = 2
            elif kind == 1:  # lift-shake: dropped, or at the end its move, contact and the table
                m = wp.length(rel - wp.vec3(fp[w, rr], fp[w, rr + 1], fp[w, rr + 2]))
                gone = touch[w] == 0 and m >= max_slip
                if gone or code == 2:
                    fp[w, mv] = m
                    fp[w, rt] = angle(quat, ref_q)
                    ip[w, col[19]] = wp.where(touch[w] == 0, 1, 0)
                    ip[w, col[20]] = table[w]
                    ip[w, st] = 1
            else:  # a push: the largest move and turn so far
                m = wp.max(fp[w, mv], wp.length(pos - wp.vec3(fp[w, rp], fp[w, rp + 1], fp[w, rp + 2])))
                r = wp.max(fp[w, rt], angle(quat, ref_q))
                fp[w, mv] = m
                fp[w, rt] = r
                if m >= max_move or r >= max_rot or code == 2:
                    ip[w, st] = 1
            p += 1
        ip[w, col[2]] = p
        ip[w, col[1]] = t + 1

    @wp.kernel
    def place(idx: wp.array(dtype=int), ip_new: wp.array2d(dtype=int), fp_new: wp.array2d(dtype=float),
              qpos_new: wp.array2d(dtype=float), qvel_new: wp.array2d(dtype=float),
              warm_new: wp.array2d(dtype=float), ip: wp.array2d(dtype=int), fp: wp.array2d(dtype=float),
              qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float), warm: wp.array2d(dtype=float),
              overflow: wp.array(dtype=int)):
        r = wp.tid()
        w = idx[r]
        for i in range(ip.shape[1]):
            ip[w, i] = ip_new[r, i]
        for i in range(fp.shape[1]):
            fp[w, i] = fp_new[r, i]
        for i in range(qpos.shape[1]):
            qpos[w, i] = qpos_new[r, i]
        for i in range(qvel.shape[1]):
            qvel[w, i] = qvel_new[r, i]
            warm[w, i] = warm_new[r, i]
        overflow[w] = 0

    @wp.kernel
    def gather(idx: wp.array(dtype=int), ip: wp.array2d(dtype=int), fp: wp.array2d(dtype=float),
               col: wp.array(dtype=int), slots: wp.array(dtype=int), obj_body: int, obj_dof: int,
               nparts: wp.array(dtype=int), part_adr: wp.array(dtype=int), mesh_first: wp.array(dtype=int),
               part_dataid: wp.array(dtype=int), part_pos: wp.array(dtype=wp.vec3),
               part_quat: wp.array(dtype=wp.quat), part_size: wp.array(dtype=wp.vec3),
               part_aabb: wp.array2d(dtype=wp.vec3), part_rbound: wp.array(dtype=float),
               o_mass: wp.array(dtype=float), o_ipos: wp.array(dtype=wp.vec3), o_iquat: wp.array(dtype=wp.quat),
               o_inertia: wp.array(dtype=wp.vec3), o_invweight: wp.array(dtype=wp.vec2),
               o_subtree: wp.array(dtype=float), o_dofw: wp.array2d(dtype=float),
               o_friction: wp.array(dtype=wp.vec3), table_geom: int, geom_friction: wp.array2d(dtype=wp.vec3),
               geom_dataid: wp.array2d(dtype=int), geom_pos: wp.array2d(dtype=wp.vec3),
               geom_quat: wp.array2d(dtype=wp.quat), geom_size: wp.array2d(dtype=wp.vec3),
               geom_aabb: wp.array3d(dtype=wp.vec3), geom_rbound: wp.array2d(dtype=float),
               body_mass: wp.array2d(dtype=float), body_ipos: wp.array2d(dtype=wp.vec3),
               body_iquat: wp.array2d(dtype=wp.quat), body_inertia: wp.array2d(dtype=wp.vec3),
               body_invweight0: wp.array2d(dtype=wp.vec2), body_subtreemass: wp.array2d(dtype=float),
               dof_invweight0: wp.array2d(dtype=float), gravity: wp.array(dtype=wp.vec3), g: float):
        r = wp.tid()
        w = idx[r]
        o = ip[w, col[21]]
        kind = ip[w, col[0]]
        for s in range(slots.shape[0]):
            gid = slots[s]
            if s < nparts[o]:
                i = part_adr[o] + s
                geom_dataid[w, gid] = mesh_first[o] + part_dataid[i]
                geom_pos[w, gid] = part_pos[i]
                geom_quat[w, gid] = part_quat[i]
                geom_size[w, gid] = part_size[i]
                geom_aabb[w, gid, 0] = part_aabb[i, 0]
                geom_aabb[w, gid, 1] = part_aabb[i, 1]
                geom_rbound[w, gid] = part_rbound[i]
                geom_friction[w, gid] = o_friction[o]
            else:
                geom_dataid[w, gid] = -1
                geom_rbound[w, gid] = 0.0
        if table_geom >= 0:  # the object's scene gives the table the object's friction (`scene.build`)
            geom_friction[w, table_geom] = o_friction[o]
        body_mass[w, obj_body] = o_mass[o]
        body_ipos[w, obj_body] = o_ipos[o]
        body_iquat[w, obj_body] = o_iquat[o]
        body_inertia[w, obj_body] = o_inertia[o]
        body_invweight0[w, obj_body] = o_invweight[o]
        body_subtreemass[w, obj_body] = o_subtree[o]
        for i in range(6):
            dof_invweight0[w, obj_dof + i] = o_dofw[o, i]
        if kind == 1:
            gravity[w] = wp.vec3(0.0, 0.0, g)
        else:
            gravity[w] = wp.vec3(0.0, 0.0, 0.0)

    @wp.kernel
    def vacate(idx: wp.array(dtype=int), slots: wp.array(dtype=int), ip: wp.array2d(dtype=int),
               geom_dataid: wp.array2d(dtype=int), gravity: wp.array(dtype=wp.vec3)):
        w = idx[wp.tid()]
        for i in range(ip.shape[1]):
            ip[w, i] = 0
        for s in range(slots.shape[0]):
            geom_dataid[w, slots[s]] = -1  # an empty world: no object, no contacts to solve
        gravity[w] = wp.vec3(0.0, 0.0, 0.0)

    return dict(vacate=vacate, control=control, clear_flags=clear_flags, contact_flags=contact_flags, events=events,
                place=place, gather=gather)
