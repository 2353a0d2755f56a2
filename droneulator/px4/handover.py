"""Who flies a PX4 vehicle when its PX4 comes and goes: the loss rule and the hand-over to a new PX4.
The ArduPilot link (:mod:`droneulator.ardupilot.link`) follows the same rules with ``ardupilot.on_loss``.

PX4 lost while its outputs drive the rotors in the air: ``px4.on_loss`` says what the simulator does
(``land``: its controller lands the vehicle at a spot clear of the scene; ``hold``; ``fall``: rotors
stop); on the ground the rotors stop (``rest``). A PX4 that connects while the vehicle is in the air
(a restarted PX4 boots believing it is landed, and would output idle when armed) does not get the
rotors: the simulator keeps flying, and an arm in the air is refused (its outputs are not applied)
until the vehicle is on the ground and PX4 disarmed or armed there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from droneulator.controllers.flight import Mode

if TYPE_CHECKING:
    from droneulator.vehicles.vehicle import Vehicle

log = logging.getLogger(__name__)

#: above this height (m, world z) the vehicle is in the air: a new PX4 does not get its rotors
AIRBORNE_Z_M = 0.05

LossAction = Literal["rest", "fall", "hold", "land"]


def on_ground(vehicle: Vehicle) -> bool:
    """(Under the lock) the vehicle rests on the ground: no PX4 is needed to keep it safe."""
    return vehicle.state.position[2] <= AIRBORNE_Z_M and vehicle.mode in (Mode.IDLE, Mode.EXTERNAL)


def landed(vehicle: Vehicle) -> bool:
    """(Under the lock) the vehicle is down under the simulator's controller: a held PX4 may take over."""
    return vehicle.mode == Mode.IDLE and vehicle.state.position[2] <= AIRBORNE_Z_M


def loss_action(z: float, on_loss: str) -> LossAction:
    """What the simulator does with a vehicle at height ``z`` whose PX4 had the rotors and was lost."""
    if z <= AIRBORNE_Z_M:
        return "rest"
    if on_loss == "fall":
        return "fall"
    return "hold" if on_loss == "hold" else "land"


def take_over(
    vehicle: Vehicle, on_loss: str, autopilot: str = "PX4"
) -> tuple[LossAction, dict[str, Any]] | None:
    """(Under the lock) after the autopilot (PX4, or ``autopilot`` as the logs name it) was dropped: apply
    :func:`loss_action` to ``vehicle`` if its outputs drove the rotors (None otherwise: whatever flies it
    goes on). Returns the action and the loss event's data (``position``; ``spot``, the landing spot,
    for land)."""
    if vehicle.mode != Mode.EXTERNAL:
        return None
    position = vehicle.state.position
    data: dict[str, Any] = {"position": [round(float(v), 3) for v in position]}
    action = loss_action(float(position[2]), on_loss)
    if action in ("rest", "fall"):
        vehicle.motors_off()
        log.warning(
            "%s lost %s: rotors stopped", autopilot, "on the ground" if action == "rest" else "in the air"
        )
    elif action == "hold":
        vehicle.hold()
        log.warning("%s lost in the air: the simulator holds the vehicle at %s", autopilot, data["position"])
    else:
        spot = vehicle.safe_land()
        data["spot"] = [round(float(v), 3) for v in spot]
        log.warning(
            "%s lost in the air: the simulator lands the vehicle at %s (from %s)",
            autopilot,
            data["spot"],
            data["position"],
        )
    return action, data


@dataclass
class Handover:
    """Whether a connected PX4 has the rotors yet (``holding``: not yet), and whether its arm in the
    air was refused (said once, until it disarms)."""

    holding: bool = False
    arm_refused: bool = False

    def connect(self, on_the_ground: bool) -> None:
        """A PX4 connected: it has the rotors at once only with the vehicle on the ground."""
        self.holding, self.arm_refused = not on_the_ground, False

    def command(self, armed: bool, down: bool) -> Literal["wait", "refuse", "hand_over"]:
        """(While holding) PX4 sent outputs, ``armed`` or not, with the vehicle ``down`` (landed, under
        the simulator's controller): ``hand_over`` once down with PX4 disarmed, or armed there;
        ``refuse`` the first time PX4 is armed in the air (to be said); ``wait`` otherwise."""
        if not armed:
            self.arm_refused = False
            if not down:
                return "wait"
        elif self.arm_refused or not down:
            if self.arm_refused:
                return "wait"
            self.arm_refused = True
            return "refuse"
        self.holding = False
        return "hand_over"


class RotorHandover:
    """What a link to an autopilot that takes the rotors over by :class:`Handover`'s rules does on each
    of its commands while the simulator holds the vehicle: hand the rotors over once the vehicle is on the
    ground with the autopilot disarmed, or armed there; refuse, and say so, an arm in the air. A link
    class names its autopilot (``autopilot``: "PX4", "ArduPilot") and the prefix of its events."""

    autopilot: str
    event_prefix: str

    def _update_hold(self, armed: bool) -> None:
        me: Any = self
        verdict = me._handover.command(armed, landed(me.vehicle))
        if verdict == "refuse":
            reason = (
                f"{self.autopilot} armed with the vehicle in the air ({me.vehicle.mode.value} under the "
                f"simulator's controller): its outputs are not applied; it gets the rotors once the vehicle "
                f"is on the ground and {self.autopilot} is disarmed or arms there"
            )
            logging.getLogger(type(self).__module__).warning("%s", reason)
            me._event(f"{self.event_prefix}_arm_refused", reason=reason)
        elif verdict == "hand_over":
            logging.getLogger(type(self).__module__).info(
                "the vehicle is on the ground at t=%.3f s: %s has the rotors", me.world.t, self.autopilot
            )
            me._event(f"{self.event_prefix}_in_control")
            if me.on_change is not None:
                me.on_change()

