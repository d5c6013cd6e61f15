"""Scripted experts for third-party Gymnasium robot envs, for recording demos.

Each expert is a factory ``name(task, seed) -> policy`` where ``policy(raw_obs)``
takes the env's raw observation (as returned by reset/step) and returns an action
in the env's own action-space units. Experts keep a little per-episode state
(their phase), so build a fresh policy for every episode. All randomness comes
from ``np.random.default_rng(seed)``; the noise keeps demos varied and makes the
experts good but not perfect, as few-shot imitation + RL wants.

Fetch (gymnasium-robotics) obs["observation"] layout used below:
  [0:3] grip_pos, [3:6] object_pos, [6:9] object_rel_pos, [9:11] finger widths, ...
Fetch action: dx, dy, dz in [-1, 1] (scaled by 0.05 m per step) and gripper
(+1 open, -1 close).
"""
import numpy as np

BLOCK = 0.025  # half the side of the Fetch cube, metres


def _move(delta, gain=10.0):
    # P-controller toward a target; 10 x 0.05 m/step -> full speed beyond 10 cm.
    return np.clip(gain * np.asarray(delta), -1.0, 1.0)


def fetch_push(task: str = "FetchPush-v4", seed: int = 0, noise: float = 0.15):
    """Push the cube to the goal: go behind it (w.r.t. the goal), descend, push.

    The push direction is recomputed every step from the cube's current position,
    so the cube is steered back onto the line when it drifts. If the gripper ends
    up off the push line, the expert re-approaches from above.
    """
    rng = np.random.default_rng(seed)
    state = {"phase": "approach"}

    def policy(obs):
        grip, obj = obs["observation"][0:3], obs["observation"][3:6]
        goal = obs["desired_goal"]
        to_goal = goal[:2] - obj[:2]
        dist = np.linalg.norm(to_goal)
        u = to_goal / max(dist, 1e-6)
        # Contact point: gripper just behind the cube on the goal->cube line
        # (extra margin while descending so the fingers do not land on the cube).
        behind = obj[:2] - u * (BLOCK + 0.035)
        low_z = obj[2]  # push at the cube's centre height
        rel = grip[:2] - obj[:2]
        lateral = np.linalg.norm(rel - u * np.dot(rel, u))
        along = np.dot(rel, u)  # < 0 when behind the cube

        if state["phase"] == "push" and (lateral > 0.035 or along > -BLOCK):
            state["phase"] = "approach"  # lost the cube: go around it again
        if state["phase"] == "approach":
            # Hover above the contact point so we never sweep the cube sideways.
            act = _move(np.r_[behind, low_z + 0.07] - grip)
            if grip[2] < low_z + 0.05 and np.linalg.norm(grip[:2] - behind) > 0.02:
                act = np.r_[0.0, 0.0, 1.0]  # rise first, then travel
            if np.linalg.norm(grip[:2] - behind) < 0.015:
                state["phase"] = "descend"
        if state["phase"] == "descend":
            act = _move(np.r_[behind, low_z] - grip)
            if abs(grip[2] - low_z) < 0.01:
                state["phase"] = "push"
        if state["phase"] == "push":
            # Track the contact point (keeps us on the line as the cube turns or
            # drifts) plus a forward step that shrinks near the goal. Slow pushes:
            # at full speed the cube is flung ahead, tips over or leaves the table.
            fwd = u * min(0.035, dist)
            act = np.clip(_move(np.r_[obj[:2] - u * (BLOCK + 0.02) - grip[:2] + fwd,
                                      low_z - grip[2]], gain=20.0), -0.6, 0.6)
        act = np.r_[act, -1.0]  # gripper is blocked in Push anyway
        act[:3] += noise * rng.standard_normal(3)
        return np.clip(act, -1.0, 1.0).astype(np.float32)

    return policy


def fetch_pick_and_place(task: str = "FetchPickAndPlace-v4", seed: int = 0, noise: float = 0.2):
    """Classic grasp script: above cube (open) -> down -> close -> carry to goal."""
    rng = np.random.default_rng(seed)
    state = {"phase": "above", "t": 0}

    def policy(obs):
        o = obs["observation"]
        grip, obj, width = o[0:3], o[3:6], o[9] + o[10]
        goal = obs["desired_goal"]
        grip_cmd = 1.0
        if state["phase"] == "above":
            target = obj + np.r_[0.0, 0.0, 0.05]
            if np.linalg.norm(grip[:2] - obj[:2]) < 0.01:
                state["phase"] = "down"
        if state["phase"] == "down":
            target = obj.copy()
            if np.linalg.norm(grip - obj) < 0.01:
                state["phase"], state["t"] = "close", 0
        if state["phase"] == "close":
            # Hold position for a few steps while the fingers close on the cube.
            target, grip_cmd = grip.copy(), -1.0
            state["t"] += 1
            if state["t"] >= 3:
                state["phase"] = "carry"
        if state["phase"] == "carry":
            target, grip_cmd = goal.copy(), -1.0
            if np.linalg.norm(obj - grip) > 0.03 or width < 0.02:
                state["phase"] = "above"  # dropped / missed it: try again
        act = np.r_[_move(target - grip), grip_cmd]
        act[:3] += noise * rng.standard_normal(3)
        return np.clip(act, -1.0, 1.0).astype(np.float32)

    return policy


EXPERTS = {
    "FetchPush-v4": fetch_push,
    "FetchPickAndPlace-v4": fetch_pick_and_place,
}


# --------------------------------------------------------------------------
# gym-pusht PushT-v0 (obs_type="state"): obs = [agent_x, agent_y, block_x,
# block_y, block_angle], action = absolute target (x, y) in [0, 512] pixels for
# a PD-controlled disc of radius 15. The env sets space damping to 0, which
# zeroes all velocities every physics step: pushing is quasi-static (the T only
# moves while pushed), so a greedy "pick the contact that best reduces the pose
# error, push a little, re-plan" strategy works.
# T geometry in the block frame (body origin at the bar's top edge):
# bar [-60, 60] x [0, 30], stem [-15, 15] x [30, 120]; centre of gravity (0, 45).
_T_COG = np.array([0.0, 45.0])
_T_INERTIA = 3000.0  # the env sums the bar moment twice: 2 x 1500 (mass 1)
_T_POLYS = [[(-60, 0), (60, 0), (60, 30), (-60, 30)], [(-15, 30), (15, 30), (15, 120), (-15, 120)]]
# Candidate contacts (point on the surface, push direction into the block).
_T_CONTACTS = (
    [((x, 0.0), (0.0, 1.0)) for x in (-50, -25, 0, 25, 50)]          # bar top
    + [((s * x, 30.0), (0.0, -1.0)) for s in (-1, 1) for x in (40, 52)]  # bar underside (clear of stem)
    + [((s * 60.0, 15.0), (-s, 0.0)) for s in (-1, 1)]                # bar ends
    + [((s * 15.0, y), (-s, 0.0)) for s in (-1, 1) for y in (55, 85, 112)]  # stem sides
    + [((x, 120.0), (0.0, -1.0)) for x in (-10, 0, 10)]               # stem bottom
)
_PUSHER_R = 15.0
_GOAL = np.array([256.0, 256.0, np.pi / 4])  # fixed in the env, not in the state obs


def _rot(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def _in_arena(xy, margin=22.0):  # walls are at 5 and 506 px
    return bool(np.all((xy > margin) & (xy < 512 - margin)))


def pusht(task: str = "gym_pusht/PushT-v0", seed: int = 0, noise: float = 2.0):
    from shapely.geometry import LineString, Polygon
    from shapely.ops import unary_union

    rng = np.random.default_rng(seed)
    state = {"contact": None, "steps": 0}
    gyr = np.sqrt(_T_INERTIA)  # radius of gyration: weights angle vs. pixels

    def error(pos, ang):
        # Desired CoG displacement and rotation (about the CoG) to reach the goal.
        dc = (_GOAL[:2] + _rot(_GOAL[2]) @ _T_COG) - (pos + _rot(ang) @ _T_COG)
        da = (_GOAL[2] - ang + np.pi) % (2 * np.pi) - np.pi
        return np.r_[dc, gyr * da]

    def twist(k, ang):
        # Direction of (CoG velocity, gyr * angular velocity) produced by an
        # impulse along the push direction at the contact (mass 1).
        p, n = (np.asarray(v, float) for v in _T_CONTACTS[k])
        r, n = _rot(ang) @ (p - _T_COG), _rot(ang) @ n
        t = np.r_[n, gyr * (r[0] * n[1] - r[1] * n[0]) / _T_INERTIA]
        return t / np.linalg.norm(t)

    def reachable(k, pos, R):
        p, n = (np.asarray(v, float) for v in _T_CONTACTS[k])
        return _in_arena(pos + R @ p - R @ n * (_PUSHER_R + 6))

    def policy(obs):
        agent, pos, ang = obs[:2], obs[2:4], obs[4]
        R = _rot(ang)
        e = error(pos, ang)
        if state["contact"] is None or state["steps"] > 8 or e @ twist(state["contact"], ang) < 1.0:
            # Re-plan: best contact for the current error (greedy), skipping
            # contacts whose pusher spot lies in/behind a wall.
            scores = [e @ twist(k, ang) if reachable(k, pos, R) else -np.inf
                      for k in range(len(_T_CONTACTS))]
            state["contact"] = int(np.argmax(scores))
            state["steps"], state["pushing"] = 0, False
        p, n = (np.asarray(v, float) for v in _T_CONTACTS[state["contact"]])
        cw, nw = pos + R @ p, R @ n
        pre = cw - nw * (_PUSHER_R + 6)
        if not state["pushing"]:
            t_shape = unary_union([Polygon([tuple(pos + R @ np.asarray(v, float)) for v in poly])
                                   for poly in _T_POLYS]).buffer(_PUSHER_R + 2)
            if np.linalg.norm(agent - pre) < 6:
                state["pushing"] = True
            elif not LineString([tuple(agent), tuple(pre)]).intersects(t_shape):
                target = pre  # clear line of sight: go straight to the pre-contact point
            else:
                # Blocked: orbit the T on a safe circle around its CoG.
                cog = pos + R @ _T_COG
                d = agent - cog
                rad = np.linalg.norm(d)
                if rad < 100:
                    target = cog + d / max(rad, 1e-6) * 110
                else:
                    a0, a1 = np.arctan2(d[1], d[0]), np.arctan2(*(pre - cog)[::-1])
                    step = np.clip((a1 - a0 + np.pi) % (2 * np.pi) - np.pi, -0.6, 0.6)
                    target = cog + 110 * np.r_[np.cos(a0 + step), np.sin(a0 + step)]
                    if not _in_arena(target):  # near a wall: orbit the other way
                        step = -np.sign(step) * 0.6
                        target = cog + 110 * np.r_[np.cos(a0 + step), np.sin(a0 + step)]
        if state["pushing"]:
            # Push into the contact; depth shrinks with the remaining error so the
            # final moves are small (success needs ~95% overlap of the T).
            depth = np.clip(0.5 * (e @ twist(state["contact"], ang)), 2.0, 25.0)
            target = cw - nw * _PUSHER_R + nw * depth
            state["steps"] += 1
        target = target + noise * rng.standard_normal(2)
        return np.clip(target, 0.0, 512.0).astype(np.float32)

    return policy


EXPERTS["gym_pusht/PushT-v0"] = pusht
