"""The haptic device models hapticd knows: one row per model, the one declaration of
what a device can do (its workspace, its force limit, and the stiffness and damping a
rendering should stay below on it).

The figures are the ones CHAI3D's cHapticDeviceInfo carries for each model
(src/devices/CDeltaDevices.cpp: m_workspaceRadius, m_maxLinearForce,
m_maxLinearStiffness, m_maxLinearDamping); the type numbers are the SDK's
dhdGetSystemType codes (DHD_DEVICE_*), left and right hand alike. A model not in
this table is refused by the backends that identify their devices: hapticd does not
guess a workspace or a force limit. A backend that meets a new model adds its row here,
and its own identification to the row (the falcon backend: the Falcon's USB IDs).

Standard library only: the device layer and the command line both read it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DeviceModel:
    """One device model: its name, the SDK's system type codes (dhdGetSystemType) that
    identify it, the radius of its translational workspace (m, a sphere about its
    origin), its continuous force limit (N), and the largest stiffness (N/m) and damping
    (N s/m) a rendering should ask of it; ``usb_ids``: the (vendor, product) IDs by which
    a backend that drives the model without its vendor's SDK finds it; ``wrist_or_gripper``:
    whether it has a wrist or a gripper beyond its three translations (the SDK then takes
    the translational force with their torques and gripper force in one call)."""

    name: str
    dhd_types: tuple[int, ...]
    workspace_radius_m: float
    max_force_n: float
    max_stiffness_n_per_m: float
    max_damping_n_s_per_m: float
    usb_ids: tuple[tuple[int, int], ...] = ()
    wrist_or_gripper: bool = False


MODELS: tuple[DeviceModel, ...] = (
    DeviceModel("delta.3", (63,), 0.15, 20.0, 5000.0, 30.0),
    DeviceModel("omega.3", (33,), 0.075, 12.0, 5000.0, 30.0),
    DeviceModel("omega.6", (34, 36), 0.075, 12.0, 5000.0, 30.0, wrist_or_gripper=True),
    DeviceModel("omega.7", (35, 37), 0.075, 12.0, 5000.0, 30.0, wrist_or_gripper=True),
    DeviceModel("sigma.7", (104, 105), 0.075, 12.0, 4000.0, 30.0, wrist_or_gripper=True),
    DeviceModel("lambda.7", (108, 109), 0.1125, 12.0, 8000.0, 30.0, wrist_or_gripper=True),
    # USB IDs: the Falcon's FTDI chip (libnifalcon, FalconComm.h).
    DeviceModel("Falcon", (60,), 0.04, 8.0, 3000.0, 20.0, ((0x0403, 0xCB48),)),
)


def model_names() -> list[str]:
    return [m.name for m in MODELS]


def by_name(name: str) -> DeviceModel | None:
    """The row named ``name`` (case-insensitive), or None."""
    for m in MODELS:
        if m.name.lower() == name.lower():
            return m
    return None


def by_dhd_type(system_type: int) -> DeviceModel | None:
    """The row whose SDK system type (dhdGetSystemType) is ``system_type``, or None."""
    for m in MODELS:
        if system_type in m.dhd_types:
            return m
    return None


def by_usb_id(vendor: int, product: int) -> DeviceModel | None:
    """The row a device with these USB IDs is, or None."""
    for m in MODELS:
        if (vendor, product) in m.usb_ids:
            return m
    return None


def markdown_table() -> str:
    """The table as Markdown (docs/devices.md keeps a copy; a test compares)."""
    rows = [
        "| model | dhdGetSystemType | workspace radius (m) | force limit (N) | "
        "max stiffness (N/m) | max damping (N s/m) | wrist or gripper |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in MODELS:
        types = ", ".join(str(t) for t in m.dhd_types)
        rows.append(
            f"| {m.name} | {types} | {m.workspace_radius_m:g} | {m.max_force_n:g} | "
            f"{m.max_stiffness_n_per_m:g} | {m.max_damping_n_s_per_m:g} | "
            f"{'yes' if m.wrist_or_gripper else 'no'} |"
        )
    return "\n".join(rows) + "\n"
