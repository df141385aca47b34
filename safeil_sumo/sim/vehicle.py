"""The ego vehicle plant: a dynamic single-track model of a Toyota Prius — pure Python floats.

The paper validated its planners on a 15-DOF Simcenter Amesim model identified from the Prius
Carlab's driving data. We do not have that model; this is our open substitute, sized from public
spec sheets and textbook values, with the effects that matter for a trajectory tracker on a
highway: actuator lags and limits, tyre side slip (understeer), aerodynamic drag, rolling
resistance and the drive's power limit.

Model (states in :class:`VehicleState`):
- Steering: first-order lag on the road-wheel angle with angle and rate limits.
- Longitudinal: one actuator force ``drive_force`` (traction > 0, braking < 0) following its target
  ``throttle * F_drive(v) - brake * F_brake`` with a first-order lag; ``F_drive(v)`` is limited by
  a maximum force and a maximum power at the wheels.
  ``m dvx/dt = F_x - F_yf sin(delta) - F_drag - F_roll + m vy r``. No reversing: ``vx >= 0``, and
  brakes (or resistances) at standstill hold the car.
- Lateral (``vx`` above ~4 m/s): linear tyres with cornering stiffness per axle, forces saturated
  at ``mu * F_z`` through a secant stiffness, integrated with implicit (backward) Euler so the stiff
  low-speed lateral modes stay stable at any step size.
- Low speed (below ~2 m/s): the dynamic model is singular at ``vx -> 0``; the lateral states come
  from the kinematic bicycle (``r = vx tan(delta) / L``, ``vy = lr r``), with a smoothstep blend
  between 2 and 4 m/s.

The world pose is integrated with the updated velocities (semi-implicit Euler).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import ClassVar, TypeAlias, cast

from safeil_sumo.sim.xp import FLOATS, FloatOrArray, Namespace

GRAVITY = 9.81  # [m/s^2]


@dataclass(frozen=True)
class VehicleParams:
    """Toyota Prius (4th gen, XW50, 2016-2022; 3rd gen XW30 where noted) with driver and equipment.

    Fields with SOURCE comments; "spec" = Toyota's published specification sheets.
    """

    mass_kg: float = 1500.0  # [kg] spec curb mass 1380-1400 kg + driver (75 kg) + logging equipment
    wheelbase_m: float = 2.70  # [m] spec (XW30 and XW50)
    length_m: float = 4.54  # [m] spec (XW50; XW30 4.48 m)
    width_m: float = 1.76  # [m] spec (body, without mirrors)
    track_width_m: float = 1.53  # [m] spec front tread 1530 mm (rear 1540 mm)
    front_overhang_m: float = 0.925  # [m] spec front overhang (front axle to front bumper)
    # CoG: ~58-60 % of the mass on the front axle (front-engine FWD hybrid, spec axle loads)
    front_axle_load_fraction: float = 0.58  # [-] F_z,front / (m g)
    yaw_inertia_kgm2: float = 2600.0  # [kg m^2] textbook I_z ~ m lf lr for a C-segment sedan
    # tyre cornering stiffness per AXLE (two tyres); 195/65 R15 low-rolling-resistance tyres,
    # textbook range 80-150 kN/rad per axle; rear stiffer than front -> understeer ~1.7 deg/g
    cornering_stiffness_front_npr: float = 110_000.0  # [N/rad]
    cornering_stiffness_rear_npr: float = 130_000.0  # [N/rad]
    friction_coefficient: float = 1.0  # [-] dry asphalt peak mu (textbook)
    drag_coefficient: float = 0.24  # [-] spec Cd 0.24 (XW50; XW30 0.25)
    frontal_area_m2: float = 2.2  # [m^2] literature ~2.2 m^2 (width x height x ~0.85)
    air_density_kgm3: float = 1.225  # [kg/m^3] ISA sea level
    rolling_resistance: float = 0.010  # [-] textbook c_rr of low-rolling-resistance tyres
    max_drive_force_n: float = 4500.0  # [N] traction/torque limit; gives 0-100 km/h in ~10 s
    max_drive_power_w: float = 81_000.0  # [W] spec system power 90 kW x ~0.9 drivetrain eff.
    max_brake_decel_mps2: float = 9.0  # [m/s^2] full braking on dry asphalt (ABS, mu ~0.9-1)
    max_steer_rad: float = 0.61  # [rad] ~35 deg road-wheel lock (turning circle 10.2 m, spec)
    max_steer_rate_radps: float = 0.6  # [rad/s] road wheel; ~480 deg/s at the handwheel / 14
    steer_time_constant_s: float = 0.1  # [s] EPS actuator lag (literature)
    drive_time_constant_s: float = 0.3  # [s] powertrain torque response (literature)
    brake_time_constant_s: float = 0.15  # [s] brake pressure build-up (literature)
    kinematic_speed_low_mps: float = 2.0  # [m/s] below: purely kinematic lateral states
    kinematic_speed_high_mps: float = 4.0  # [m/s] above: purely dynamic lateral states
    # derived, set in __post_init__
    lf_m: float = field(init=False)  # [m] CoG to front axle
    lr_m: float = field(init=False)  # [m] CoG to rear axle

    def __post_init__(self) -> None:
        object.__setattr__(self, "lf_m", (1.0 - self.front_axle_load_fraction) * self.wheelbase_m)
        object.__setattr__(self, "lr_m", self.front_axle_load_fraction * self.wheelbase_m)

    @property
    def track_m(self) -> float:
        """Wheel track [m] (tread, wheel centre to wheel centre)."""
        return self.track_width_m

    @property
    def barrier_width_m(self) -> float:
        """Width ``T`` [m] for the paper's lane barrier: "the track, i.e. the width" -> body width."""
        return self.width_m

    @property
    def cog_to_front_bumper_m(self) -> float:
        """Distance [m] from the CoG forward to the front bumper."""
        return self.lf_m + self.front_overhang_m

    @cached_property  # read every physics step by the tracker
    def understeer_gradient(self) -> float:
        """``K_us`` [rad/(m/s^2)]: steady state ``delta = L / R + K_us a_y`` of the linear model."""
        m, L = self.mass_kg, self.wheelbase_m
        cf, cr = self.cornering_stiffness_front_npr, self.cornering_stiffness_rear_npr
        return m / L * (self.lr_m / cf - self.lf_m / cr)

    @cached_property  # read every physics step (pedals_from_accel_vx)
    def max_brake_force_n(self) -> float:
        """Brake force [N] at full pedal."""
        return self.mass_kg * self.max_brake_decel_mps2


@dataclass(frozen=True, slots=True)
class VehicleState:
    """State of the plant; positions in the world frame, velocities in the body frame."""

    x: float  # [m] CoG, world
    y: float  # [m] CoG, world
    yaw: float  # [rad] heading, counter-clockwise from world +x (not wrapped)
    vx: float  # [m/s] longitudinal velocity of the CoG, body frame (>= 0)
    vy: float  # [m/s] lateral velocity of the CoG, body frame (left +)
    yaw_rate: float  # [rad/s] counter-clockwise +
    steer: float  # [rad] actual road-wheel angle (left +)
    drive_force: float  # [N] actual longitudinal tyre force: traction > 0, braking < 0


def speed(state: VehicleState) -> float:
    """Speed [m/s] of the CoG."""
    return math.hypot(state.vx, state.vy)


def resistance_force(vx: FloatOrArray, params: VehicleParams, xp: Namespace = FLOATS
                     ) -> FloatOrArray:
    """Drag + rolling resistance [N] opposing motion at ``vx`` [m/s] (0 at standstill; a
    float, or an array with ``xp=ARRAYS``)."""
    drag = 0.5 * params.air_density_kgm3 * params.drag_coefficient * params.frontal_area_m2
    return xp.where(vx <= 0.0, 0.0,
                    drag * vx * vx + params.rolling_resistance * params.mass_kg * GRAVITY)


def available_drive_force(vx: FloatOrArray, params: VehicleParams, xp: Namespace = FLOATS
                          ) -> FloatOrArray:
    """Traction force [N] at full throttle: force-limited at low speed, power-limited above
    (``vx`` [m/s] a float, or an array with ``xp=ARRAYS``)."""
    return xp.minimum(params.max_drive_force_n, params.max_drive_power_w / xp.maximum(vx, 0.1))


def pedals_from_accel(
    accel_cmd: float, state: VehicleState, params: VehicleParams
) -> tuple[float, float]:
    """Throttle and brake in [0, 1] that realise ``accel_cmd`` [m/s^2] once the actuator settles.

    Inverse of the longitudinal model with drag and rolling resistance as feed-forward; exactly one
    of the two is non-zero (or both zero). Saturates at full throttle / full brake.
    """
    # FLOATS (the default) on floats gives floats
    return cast("tuple[float, float]", pedals_from_accel_vx(accel_cmd, state.vx, params))


def pedals_from_accel_vx(accel_cmd: FloatOrArray, vx: FloatOrArray, params: VehicleParams,
                         xp: Namespace = FLOATS) -> tuple[FloatOrArray, FloatOrArray]:
    """:func:`pedals_from_accel` from the longitudinal speed ``vx`` [m/s] alone (floats, or
    arrays ``(N,)`` with ``xp=ARRAYS``)."""
    force = params.mass_kg * accel_cmd + resistance_force(vx, params, xp)
    throttle = xp.where(force > 0.0,
                        xp.minimum(force / available_drive_force(vx, params, xp), 1.0), 0.0)
    brake = xp.where(force < 0.0, xp.minimum(-force / params.max_brake_force_n, 1.0), 0.0)
    return throttle, brake


def _lag(value: float, target: float, time_constant: float, dt: float) -> float:
    """Exact discretisation of a first-order lag over ``dt``."""
    if time_constant <= 0.0:
        return target
    return target + (value - target) * math.exp(-dt / time_constant)


def step(
    state: VehicleState,
    steer_cmd: float,
    throttle: float,
    brake: float,
    params: VehicleParams,
    dt: float,
) -> VehicleState:
    """Advance the plant by ``dt`` [s] under road-wheel ``steer_cmd`` [rad] and pedals in [0, 1]."""
    s = state
    fields = Plant.of(params, dt).step(
        (s.x, s.y, s.yaw, s.vx, s.vy, s.yaw_rate, s.steer, s.drive_force),
        steer_cmd, throttle, brake)
    return VehicleState(*cast("tuple[float, ...]", fields))  # FLOATS on floats gives floats


_TINY = 1e-300  # a divisor's floor on the untaken side of a branch

# the plant's state as :class:`Plant` steps it: the :class:`VehicleState` fields in order, floats
# (one car) or arrays (N,) (N cars)
PlantState: TypeAlias = tuple[FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray,
                              FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray]


class Plant:
    """:func:`step` on a plain tuple of the :class:`VehicleState` fields, in field order.

    The parameter-only terms (lag factors, drag and rolling-resistance constants, axle loads) are
    computed once per ``(params, dt)`` with the same expressions, so the result is bit-identical
    to evaluating them every step; the closed loop keeps its state as a tuple (no per-step
    dataclass) and calls :meth:`step` directly.
    """

    _cache: ClassVar[dict[tuple[int, float], Plant]] = {}

    def __init__(self, params: VehicleParams, dt: float) -> None:
        p = params
        self.params = p
        self.dt = dt
        self.steer_gain = 1.0 - math.exp(-dt / p.steer_time_constant_s)
        self.max_d_steer = p.max_steer_rate_radps * dt
        # _lag's factors exp(-dt / tau); None: no lag (tau <= 0)
        self.brake_decay = math.exp(-dt / p.brake_time_constant_s) if (
            p.brake_time_constant_s > 0.0) else None
        self.drive_decay = math.exp(-dt / p.drive_time_constant_s) if (
            p.drive_time_constant_s > 0.0) else None
        self.drag = 0.5 * p.air_density_kgm3 * p.drag_coefficient * p.frontal_area_m2
        self.rolling = p.rolling_resistance * p.mass_kg * GRAVITY
        self.max_brake_force = p.max_brake_force_n
        self.fzf = p.front_axle_load_fraction * p.mass_kg * GRAVITY
        self.fzr = p.mass_kg * GRAVITY - self.fzf
        self.v_band = p.kinematic_speed_high_mps - p.kinematic_speed_low_mps

    @classmethod
    def of(cls, params: VehicleParams, dt: float) -> Plant:
        """The plant of ``params`` and ``dt``, cached (``params`` is immutable)."""
        key = (id(params), dt)
        plant = cls._cache.get(key)
        if plant is None or plant.params is not params:
            if len(cls._cache) > 64:
                cls._cache.clear()
            plant = cls._cache[key] = cls(params, dt)
        return plant

    def actuators(self, steer0: FloatOrArray, force0: FloatOrArray, vx: FloatOrArray,
                  steer_cmd: FloatOrArray, throttle: FloatOrArray, brake: FloatOrArray,
                  xp: Namespace = FLOATS) -> tuple[FloatOrArray, FloatOrArray]:
        """The actuators' next ``(steer, drive_force)``: road-wheel angle [rad] from ``steer0``
        under ``steer_cmd`` (clipped, rate-limited, first-order lag), and the longitudinal tyre
        force [N] from ``force0`` under the pedals at speed ``vx`` [m/s] (brake or drive lag)."""
        p = self.params
        clip = xp.clip
        max_steer = p.max_steer_rad
        cmd = clip(steer_cmd, -max_steer, max_steer)
        d_steer = (cmd - steer0) * self.steer_gain
        max_d = self.max_d_steer
        delta = steer0 + clip(d_steer, -max_d, max_d)

        throttle = clip(throttle, 0.0, 1.0)
        brake = clip(brake, 0.0, 1.0)
        # available_drive_force, inline (a call per step saved)
        drive = xp.minimum(p.max_drive_force_n, p.max_drive_power_w / xp.maximum(vx, 0.1))
        target = throttle * drive - brake * self.max_brake_force
        # brake circuit dynamics whenever braking is involved (applying or releasing); a first-
        # order lag, or none for a time constant <= 0 (decay None)
        braking = (target < 0.0) | (force0 < 0.0)  # flags: | is logical_or
        fx_brake = target if self.brake_decay is None else (
            target + (force0 - target) * self.brake_decay)
        fx_drive = target if self.drive_decay is None else (
            target + (force0 - target) * self.drive_decay)
        return delta, xp.where(braking, fx_brake, fx_drive)

    def step(self, state: PlantState, steer_cmd: FloatOrArray, throttle: FloatOrArray,
             brake: FloatOrArray, xp: Namespace = FLOATS) -> PlantState:
        """Next ``(x, y, yaw, vx, vy, yaw_rate, steer, drive_force)`` (see :func:`step`).

        ``state`` is a tuple of those 8 fields and the commands are floats, or with
        ``xp=ARRAYS`` each is an array ``(N,)`` of N cars stepped at once (see :mod:`.xp`).
        """
        p = self.params
        dt = self.dt
        m, lf, lr, L = p.mass_kg, p.lf_m, p.lr_m, p.wheelbase_m
        x0, y0, yaw0, vx, vy, r, steer0, force0 = state
        where, clip = xp.where, xp.clip
        delta, fx = self.actuators(steer0, force0, vx, steer_cmd, throttle, brake, xp)

        # --- lateral: dynamic single track, implicit Euler with secant tyre stiffness -----------
        v_lo = p.kinematic_speed_low_mps
        w = clip((vx - v_lo) / self.v_band, 0.0, 1.0)
        w = w * w * (3.0 - 2.0 * w)  # smoothstep: weight of the dynamic model
        dynamic = w > 0.0  # below v_lo the dynamic terms are computed but not used
        u = xp.maximum(vx, v_lo)
        alpha_f = delta - (vy + lf * r) / u
        alpha_r = -(vy - lr * r) / u
        cf = p.cornering_stiffness_front_npr
        cr = p.cornering_stiffness_rear_npr
        mu = p.friction_coefficient
        # saturate |F_y| at mu F_z by lowering the stiffness to the secant through the limit (the
        # floor only keeps the untaken side finite: where it is taken |alpha| > mu F_z / C > 0)
        abs_f, abs_r = xp.abs(alpha_f), xp.abs(alpha_r)
        cf = where(cf * abs_f > mu * self.fzf, mu * self.fzf / xp.maximum(abs_f, _TINY), cf)
        cr = where(cr * abs_r > mu * self.fzr, mu * self.fzr / xp.maximum(abs_r, _TINY), cr)
        iz = p.yaw_inertia_kgm2
        a11 = -(cf + cr) / (m * u)
        a12 = -(lf * cf - lr * cr) / (m * u) - u
        a21 = -(lf * cf - lr * cr) / (iz * u)
        a22 = -(lf * lf * cf + lr * lr * cr) / (iz * u)
        b1 = vy + dt * cf * delta / m
        b2 = r + dt * lf * cf * delta / iz
        # (I - dt A) [vy, r]' = [b1, b2]'
        m11, m12, m21, m22 = 1.0 - dt * a11, -dt * a12, -dt * a21, 1.0 - dt * a22
        det = m11 * m22 - m12 * m21
        vy_dyn = (b1 * m22 - m12 * b2) / det
        r_dyn = (m11 * b2 - m21 * b1) / det
        fyf = where(dynamic, cf * (delta - (vy_dyn + lf * r_dyn) / u), 0.0)

        # --- longitudinal ----------------------------------------------------------------------
        resistance = where(vx <= 0.0, 0.0, self.drag * vx * vx + self.rolling)  # resistance_force
        ax = (fx - resistance - w * fyf * xp.sin(delta)) / m + w * vy * r
        # no reversing: brakes and resistances hold the car at standstill
        vx_new = xp.maximum(vx + ax * dt, 0.0)

        # --- blend with the kinematic bicycle at low speed --------------------------------------
        r_kin = vx_new * xp.tan(delta) / L
        vy_kin = lr * r_kin
        vy_new = where(dynamic, w * vy_dyn + (1.0 - w) * vy_kin, vy_kin)
        r_new = where(dynamic, w * r_dyn + (1.0 - w) * r_kin, r_kin)

        # --- pose (semi-implicit Euler: updated velocities) ------------------------------------
        yaw = yaw0 + r_new * dt
        c, s = xp.cos(yaw), xp.sin(yaw)
        return (
            x0 + (vx_new * c - vy_new * s) * dt,
            y0 + (vx_new * s + vy_new * c) * dt,
            yaw,
            vx_new,
            vy_new,
            r_new,
            delta,
            fx,
        )


def front_bumper(state: VehicleState, params: VehicleParams) -> tuple[float, float]:
    """World position [m] of the front-bumper centre (SUMO's vehicle position)."""
    d = params.cog_to_front_bumper_m
    return state.x + d * math.cos(state.yaw), state.y + d * math.sin(state.yaw)


def rear_axle(state: VehicleState, params: VehicleParams) -> tuple[float, float]:
    """World position [m] of the rear-axle centre (pure pursuit's reference point)."""
    d = params.lr_m
    return state.x - d * math.cos(state.yaw), state.y - d * math.sin(state.yaw)


def state_from_front_bumper(
    x: float, y: float, yaw: float, speed: float, params: VehicleParams
) -> VehicleState:
    """Straight-running state with the front bumper at ``(x, y)`` [m], heading ``yaw`` [rad].

    The drive force balances drag and rolling resistance, so the car holds ``speed`` [m/s] at the
    matching throttle (see :func:`pedals_from_accel` with zero acceleration).
    """
    d = params.cog_to_front_bumper_m
    v = max(speed, 0.0)
    return VehicleState(
        x=x - d * math.cos(yaw),
        y=y - d * math.sin(yaw),
        yaw=yaw,
        vx=v,
        vy=0.0,
        yaw_rate=0.0,
        steer=0.0,
        drive_force=cast(float, resistance_force(v, params)),  # FLOATS on a float: a float
    )
