"""One rendering step: device positions -> proxies -> contact forces -> allocation.

``Renderer.step`` runs once per servo tick. Outputs live in preallocated
arrays on the renderer (shapes with F fingers, r actuators):

- proxy_pos (F, 3) m, in_contact (F,) bool, contact_point (F, 3) m;
- contact_force (F, 3) N: the full force lam_i = k (proxy - device) - b v on
  each finger (the negative of the seed's force on the object; every allocator
  is linear, so this only flips the sign of lam_a);
- lam_a (r,) N and rendered_force (F, 3) N = finger i's rows of M_a lam_a,
  zero for a finger out of contact.
"""

from __future__ import annotations

import numpy as np

from hapticd.actuation import Actuation
from hapticd.allocation import allocate
from hapticd.contact import update_proxy
from hapticd.grasp import grasp_matrix
from hapticd.scene import SceneObject


class Renderer:
    """Proxy contact of F spherical fingertips on one object, then force allocation."""

    def __init__(
        self,
        obj: SceneObject,
        radii: list[float],
        actuation: Actuation,
        allocator: str,
    ) -> None:
        if len(radii) != actuation.n_fingers:
            raise ValueError("one radius per finger is needed")
        self.obj = obj
        self.radii = [float(r) for r in radii]
        self.polys = [obj.polytope.inflated(r) for r in self.radii]
        self.actuation = actuation
        self.allocator = allocator
        F, r = actuation.n_fingers, actuation.n_actuators
        self.n_fingers = F
        self.proxy_pos = np.zeros((F, 3))
        self.in_contact = np.zeros(F, dtype=bool)
        self.contact_point = np.zeros((F, 3))
        self.contact_force = np.zeros((F, 3))
        self.rendered_force = np.zeros((F, 3))
        self.lam_a = np.zeros(r)
        self._normals = np.zeros((F, 3))
        self._started = False

    def reset(self, device_pos: np.ndarray) -> None:
        """Start every proxy at its device (pushed out of the object if inside)."""
        self.proxy_pos[:] = device_pos
        self._started = True

    def step(self, device_pos: np.ndarray, device_vel: np.ndarray) -> None:
        """Update proxies and forces for device positions (F, 3) m and velocities (F, 3) m/s."""
        if not self._started:
            self.reset(device_pos)
        k, b = self.obj.stiffness, self.obj.damping
        contacts: list[int] = []
        for i in range(self.n_fingers):
            res = update_proxy(self.polys[i], self.proxy_pos[i], device_pos[i])
            self.proxy_pos[i] = res.proxy
            self.in_contact[i] = res.in_contact
            if res.in_contact:
                n = res.normal
                f = k * (res.proxy - device_pos[i])
                if b:
                    f -= b * device_vel[i]
                    # Damping may slow the finger but never pull it into the object.
                    fn = float(f @ n)
                    if fn < 0.0:
                        f -= fn * n
                self.contact_force[i] = f
                self._normals[i] = n
                self.contact_point[i] = res.proxy - self.radii[i] * n
                contacts.append(i)
            else:
                self.contact_force[i] = 0.0
                self._normals[i] = 0.0
                self.contact_point[i] = res.proxy
        self.rendered_force[:] = 0.0
        self.lam_a[:] = 0.0
        if not contacts:
            return
        M = self.actuation.matrix(device_pos)
        M_sub, cols = self.actuation.select(M, contacts)
        if M_sub.shape[1] == 0:
            return
        G = grasp_matrix(self.contact_point[contacts], self.obj.center)
        lam = self.contact_force[contacts].reshape(-1)
        lam_a = allocate(self.allocator, G, M_sub, lam)
        self.lam_a[cols] = lam_a
        self.rendered_force[contacts] = (M_sub @ lam_a).reshape(-1, 3)
