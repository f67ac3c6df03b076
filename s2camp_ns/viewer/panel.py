"""The viewer's "S2CamP" panel and training-camera frusta: camera refinement, watched live.

The model declares the panel (``S2CampModel.S2CamP``) and serves it through ``CameraRefinementSource``. nerfstudio's
viewer installs it (Custom Elements > model > S2CamP) and hands its ``Viewer`` to the panel's ``ViewerControl``; only
then does the model add its training callback (``refinement.viewer_panel_callbacks``), which calls ``update`` once per
``update_period`` or after a refresh of P, so a training step runs this module only then.

Shown, at most every ``update_period`` seconds: camera errors (mean / max), the condition number of each camera's Gram
matrix Sigma (from P's last refresh; the initial cameras' after a resume) before and after whitening, the steps since
that refresh and a button that requests one. Frusta: the refined training cameras (amber) and, when the reference
cameras differ from the initial ones, those two sets (red, green); a click moves the view to that camera.

Nothing here may stop training: a failure is reported once and the panel then stays still. viser's ``atomic()`` is
never used (its lock is not released when its block raises, which freezes the viewer).
"""

from __future__ import annotations

import math
import threading
import time
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
import torch
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerCheckbox, ViewerControl, ViewerText
from torch import Tensor, nn

from s2camp_ns.core.preconditioner import condition_number

if TYPE_CHECKING:
    from viser import ViserServer

FrustumSet = Literal["refined", "initial", "reference"]
FRUSTUM_COLORS: dict[FrustumSet, tuple[int, int, int]] = {
    "refined": (255, 176, 32),
    "initial": (230, 64, 64),
    "reference": (64, 200, 110),
}
FRUSTUM_ROOT = "/s2camp_cameras"
"""Scene-tree folder of the panel's frusta (nerfstudio's own are under /cameras)."""
MAX_DRAWN_FOV = math.radians(170.0)
"""Widest field of view drawn (a perspective frustum ends before 180 degrees; a fisheye's may not)."""
_POSE_TOLERANCE = 1e-6
"""Frusta that moved less than this (viser units, radians) are not re-sent."""


@dataclass(frozen=True)
class CameraFrusta:
    """Cameras to draw: OpenCV c2w [n, 3, 4] (scene units), vertical field of view [n] (radians,
    ``core.camera.vertical_field_of_view``), width and height [n]."""

    c2w_cv: Tensor
    vertical_fov: Tensor
    width: Tensor
    height: Tensor


@dataclass(frozen=True)
class RefinementStatus:
    """The state of the camera refinement that the panel shows."""

    num_cameras: int
    refinement_enabled: bool
    preconditioned: bool
    last_refresh_step: int
    """Training step of the last computation of P; -1 before the first."""
    refresh_every: int
    """Steps between scheduled refreshes of P; 0 = computed once."""
    gram: Tensor | None
    """Gram matrix Sigma [n, k, k] of the last refresh; None without preconditioning or before one."""
    precond_inverse: Tensor | None
    """P^-1 [n, k, k] of the last refresh (with ``gram``)."""


class CameraRefinementSource(Protocol):
    """All the panel reads from the model (``S2CampRefinementMixin`` implements it)."""

    def refinement_status(self) -> RefinementStatus | None:
        """None until the pipeline has handed over the training cameras."""
        ...

    def camera_errors(self) -> dict[str, float]:
        """``camera_errors/*`` against the reference cameras (empty without them)."""
        ...

    def camera_frusta(self, which: FrustumSet) -> CameraFrusta | None:
        """The refined, initial or reference training cameras; "reference" is None when it equals "initial"."""
        ...

    def request_refresh(self) -> None:
        """Refresh P at the next agreed step, on every rank (thread-safe; called from rank 0's websocket thread)."""
        ...


class DisplayText(ViewerText):
    """A read-only text field written by the training thread; installed without a callback (nerfstudio re-renders
    the view on every element callback)."""

    def __init__(self, name: str, hint: str, value: str = "n/a") -> None:
        super().__init__(name, value, disabled=True, hint=hint)

    def install(self, viser_server: ViserServer) -> None:
        self._create_gui_handle(viser_server)


def _mean_max(errors: dict[str, float], key: str, scale: float = 1.0) -> str:
    """Text "mean / max" of ``camera_errors/{key}_mean`` and ``camera_errors/{key}_max``."""
    mean, worst = (errors[f"camera_errors/{key}_{stat}"] * scale for stat in ("mean", "max"))
    return f"{mean:.3g} / {worst:.3g}"


class S2CampViewerPanel(nn.Module):
    """The panel's elements (listed in attribute-name order, hence the letter prefixes), frusta and ``update``;
    no parameters or buffers, and only a weak reference to the model."""

    def __init__(self, source: CameraRefinementSource, update_period: float = 1.0) -> None:
        super().__init__()
        self._source_ref = weakref.ref(source)
        self.update_period = float(update_period)
        """Seconds between the panel's updates while training (after a refresh of P: at once)."""
        self.a_status = DisplayText("Status", "Training step of the last update, and the number of training cameras")
        self.b_errors = DisplayText("Cam. error", "The three rows below: mean / max over the training cameras", "")
        self.c_rotation_error = DisplayText(
            "Rotation °", "Geodesic rotation error (degrees) against the reference cameras after a similarity alignment"
        )
        self.d_position_error = DisplayText(
            "Position", "Camera-centre error against the reference cameras after the alignment (scene units)"
        )
        self.e_focal_error = DisplayText("Focal px", "Focal-length error against the reference cameras (pixels)")
        self.f_conditioning = DisplayText(
            "Precond.", "The two rows below: mean / worst camera, from the Gram matrix Σ of the last refresh of P"
        )
        self.g_condition_sigma = DisplayText("cond Σ", "Condition number of each camera's Gram matrix Σ")
        self.h_condition_whitened = DisplayText(
            "cond P⁻¹ΣP⁻¹", "Condition number of Σ whitened by the damped preconditioner P"
        )
        self.i_since_refresh = DisplayText("P refreshed", "Training steps since P was last recomputed")
        self.j_refresh_now = ViewerButton("Refresh P now", cb_hook=lambda _: self.request_refresh())
        self.k_show_refined = ViewerCheckbox(
            "Refined (amber)", True, cb_hook=lambda element: self.set_frusta_visible("refined", element.value)
        )
        self.l_show_initial = ViewerCheckbox(
            "Initial (red)", True, cb_hook=lambda element: self.set_frusta_visible("initial", element.value)
        )
        self.m_show_reference = ViewerCheckbox(
            "Reference (green)", True, cb_hook=lambda element: self.set_frusta_visible("reference", element.value)
        )
        self.viewer_control = _PanelControl(self)
        self._viewer: Any = None
        self._lock = threading.Lock()  # guards the frustum handles (training thread vs. websocket callbacks)
        self._handles: dict[FrustumSet, dict[int, Any]] = {"refined": {}, "initial": {}, "reference": {}}
        self._poses: dict[FrustumSet, dict[int, tuple[np.ndarray, np.ndarray, float]]] = {n: {} for n in self._handles}
        self._nerfstudio_frusta_hooked = False
        self.shown_refresh_step: int | None = None  # the refresh of P the panel shows
        self.last_update = -math.inf  # time.monotonic() of the last update
        self._failed = False
        self.num_updates = 0

    def _source(self) -> CameraRefinementSource:
        # A method, not a property: nerfstudio's viewer walks public attributes (properties included) for elements.
        source = self._source_ref()
        if source is None:
            raise RuntimeError("the S2CamP viewer panel outlived its model")
        return source

    @property
    def attached(self) -> bool:
        """True once nerfstudio's viewer has installed the panel (and no error has disabled it)."""
        return self._viewer is not None and not self._failed

    def request_refresh(self) -> None:
        """Ask the model for a refresh of P at its next training step (called from the viewer's websocket thread)."""
        self._source().request_refresh()

    def attach(self, viewer: Any) -> None:
        """Called by the ViewerControl once the viewer is built: draw the static frusta, fill the panel."""
        self._viewer = viewer
        self._guard(self._attach)

    @torch.no_grad()
    def _attach(self) -> None:
        status = self._source().refinement_status()
        if status is None:
            return
        distinct = self._source().camera_frusta("reference") is not None
        for element in (self.l_show_initial, self.m_show_reference):
            element.set_visible(distinct)
        # No training (ns-viewer has no trainer), no refinement or no preconditioning: nothing to refresh.
        refreshable = status.refinement_enabled and status.preconditioned
        if getattr(self._viewer, "trainer", None) is None or not refreshable:
            self.j_refresh_now.set_disabled(True)
        if distinct:
            self._draw_static_sets()
        self._update(step=max(status.last_refresh_step, 0))

    def _guard(self, func, *args) -> None:
        if self._failed:
            return
        try:
            func(*args)
        except Exception as error:  # the viewer must never stop training
            self._failed = True
            CONSOLE.print(
                f"[bold yellow]S2CamP viewer panel disabled after an error ({type(error).__name__}: {error}); "
                "training continues."
            )

    def update(self, step: int) -> None:
        """Show the model's state at training step ``step`` (the model's training callback decides when)."""
        self._guard(self._update, step)

    @torch.no_grad()
    def panel_values(self, step: int) -> dict[str, str]:
        """The panel's text values at training step ``step`` (also used by tests)."""
        source = self._source()
        status = source.refinement_status()
        assert status is not None
        values = {"a_status": f"step {step} · {status.num_cameras} cams"}
        errors = source.camera_errors()
        if errors:
            values["b_errors"] = "mean / max"
            values["c_rotation_error"] = _mean_max(errors, "rot_err", scale=180.0 / math.pi)
            values["d_position_error"] = _mean_max(errors, "pos_err")
            has_focal = "camera_errors/focal_err_mean" in errors
            values["e_focal_error"] = _mean_max(errors, "focal_err") if has_focal else "n/a"
        else:
            values["b_errors"] = "no reference cameras"
            values["c_rotation_error"] = values["d_position_error"] = values["e_focal_error"] = "n/a"
        gram, inverse = status.gram, status.precond_inverse
        if gram is not None and inverse is not None:
            inverse = inverse.to(gram)
            whitened = inverse.transpose(-1, -2) @ gram @ inverse
            values["f_conditioning"] = "mean / worst"
            values["g_condition_sigma"] = self._condition_text(gram)
            values["h_condition_whitened"] = self._condition_text(0.5 * (whitened + whitened.transpose(-1, -2)))
        else:
            values["f_conditioning"] = "preconditioning off" if status.refinement_enabled else "camera refinement off"
            values["g_condition_sigma"] = values["h_condition_whitened"] = "n/a"
        last, every = status.last_refresh_step, status.refresh_every
        since = f"{max(step - last, 0)} steps ago" if last >= 0 else "never"
        if every > 0 and last >= 0:
            since += f" (every {every})"
        values["i_since_refresh"] = since
        return values

    @staticmethod
    def _condition_text(matrices: torch.Tensor) -> str:
        condition = condition_number(matrices)
        return f"{float(condition.mean()):.3g} / {float(condition.max()):.3g}"

    @torch.no_grad()
    def _update(self, step: int) -> None:
        status = self._source().refinement_status()
        self.shown_refresh_step = None if status is None else status.last_refresh_step
        values = self.panel_values(step)
        for name, value in values.items():
            element = getattr(self, name)
            if element.value != value:
                element.value = value
        self._update_refined_frusta()
        if not self._nerfstudio_frusta_hooked:
            self._hook_nerfstudio_frusta()
        self._show_step_in_viewer_header(step)
        self.last_update = time.monotonic()
        self.num_updates += 1

    def _show_step_in_viewer_header(self, step: int) -> None:
        """Set nerfstudio's "Step: N" line to the panel's step while training (nerfstudio updates it only when it
        renders a training image, rarely on a CPU); ns-viewer keeps the checkpoint's step."""
        update_step = getattr(self._viewer, "update_step", None)
        if update_step is not None and getattr(self._viewer, "trainer", None) is not None:
            update_step(step)

    def _server(self) -> ViserServer:
        return self._viewer.viser_server

    def _scale_ratio(self) -> float:
        from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

        return VISER_NERFSTUDIO_SCALE_RATIO

    def drawn_indices(self) -> list[int]:
        """Training cameras drawn, evenly spaced up to the viewer's ``max_num_display_images`` (as nerfstudio)."""
        status = self._source().refinement_status()
        total = 0 if status is None else status.num_cameras
        limit = getattr(getattr(self._viewer, "config", None), "max_num_display_images", -1)
        count = total if limit is None or limit < 0 else min(limit, total)
        return np.linspace(0, total - 1, count, dtype=np.int64).tolist() if count > 0 else []

    def _frustum_params(
        self, frusta: CameraFrusta, indices: list[int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Positions (viser units), wxyz, vertical fields of view (clamped) and aspect ratios of ``indices``."""
        import viser.transforms as vtf

        c2w = frusta.c2w_cv.detach().double().cpu().numpy()[indices]
        positions = c2w[:, :, 3] * self._scale_ratio()
        wxyz = vtf.SO3.from_matrix(c2w[:, :, :3]).wxyz.reshape(-1, 4)
        fov, width, height = (
            value.detach().double().cpu().numpy()[indices]
            for value in (frusta.vertical_fov, frusta.width, frusta.height)
        )
        return positions, wxyz, np.minimum(fov, MAX_DRAWN_FOV), width / height

    @torch.no_grad()
    def _draw_static_sets(self) -> None:
        indices = self.drawn_indices()
        for name in ("initial", "reference"):
            frusta = self._source().camera_frusta(name)
            if frusta is None:
                continue
            positions, wxyz, fov, aspect = self._frustum_params(frusta, indices)
            with self._lock:
                for row, index in enumerate(indices):
                    self._add_frustum(name, index, positions[row], wxyz[row], float(fov[row]), float(aspect[row]))

    def _update_refined_frusta(self) -> None:
        indices = self.drawn_indices()
        frusta = self._source().camera_frusta("refined")
        if not indices or frusta is None:
            return
        positions, wxyz, fov, aspect = self._frustum_params(frusta, indices)
        with self._lock:
            handles, poses = self._handles["refined"], self._poses["refined"]
            for row, index in enumerate(indices):
                old = poses.get(index)
                if index not in handles or old is None or abs(old[2] - float(fov[row])) > _POSE_TOLERANCE:
                    self._add_frustum("refined", index, positions[row], wxyz[row], float(fov[row]), float(aspect[row]))
                    continue
                if np.abs(old[0] - positions[row]).max() > _POSE_TOLERANCE or (
                    np.abs(np.abs(old[1] @ wxyz[row]) - 1.0) > _POSE_TOLERANCE
                ):
                    handles[index].position = positions[row]
                    handles[index].wxyz = wxyz[row]
                    poses[index] = (positions[row], wxyz[row], float(fov[row]))

    def _add_frustum(
        self, name: FrustumSet, index: int, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float
    ) -> None:
        """(Re)create one frustum (viser cannot change a frustum's field of view in place). Caller holds the lock."""
        handle = self._server().scene.add_camera_frustum(
            f"{FRUSTUM_ROOT}/{name}/camera_{index:05d}",
            fov=fov,
            aspect=aspect,
            scale=float(getattr(getattr(self._viewer, "config", None), "camera_frustum_scale", 0.1)),
            color=FRUSTUM_COLORS[name],
            wxyz=wxyz,
            position=position,
            visible=self._set_visible(name),
        )
        handle.on_click(lambda event, name=name, index=index: self._guard(self._go_to_camera, event, name, index))
        self._handles[name][index] = handle
        self._poses[name][index] = (position, wxyz, fov)

    def _set_visible(self, name: FrustumSet) -> bool:
        checkbox = {"refined": self.k_show_refined, "initial": self.l_show_initial, "reference": self.m_show_reference}
        return bool(checkbox[name].value)

    def set_frusta_visible(self, name: FrustumSet, visible: bool) -> None:
        """Show or hide one frustum set (checkbox callback, websocket thread)."""
        with self._lock:
            for handle in self._handles[name].values():
                handle.visible = bool(visible)

    def _go_to_camera(self, event: Any, name: FrustumSet, index: int) -> None:
        """Move the clicking client's view to camera ``index`` of set ``name``, field of view included."""
        with self._lock:
            pose = self._poses[name].get(index)
        if pose is None:
            return
        position, wxyz, fov = pose
        camera = event.client.camera
        camera.fov, camera.position, camera.wxyz = fov, position, wxyz
        if hasattr(self._viewer, "current_camera_idx"):
            self._viewer.current_camera_idx = index

    def _hook_nerfstudio_frusta(self) -> None:
        """Make a click on nerfstudio's own (image) training frusta also apply the refined field of view."""
        handles = getattr(self._viewer, "camera_handles", None)
        if not handles:
            return  # nerfstudio draws them when training starts
        for index, handle in handles.items():
            handle.on_click(lambda event, index=int(index): self._guard(self._go_to_camera, event, "refined", index))
        self._nerfstudio_frusta_hooked = True


class _PanelControl(ViewerControl):
    """Receives nerfstudio's viewer (``ViewerControl._setup`` is how nerfstudio hands it to a model's controls)."""

    def __init__(self, panel: S2CampViewerPanel) -> None:
        super().__init__()
        self._panel_ref = weakref.ref(panel)

    def _setup(self, viewer: Any) -> None:
        super()._setup(viewer)
        panel = self._panel_ref()
        if panel is not None:
            panel.attach(viewer)


__all__ = [
    "FRUSTUM_COLORS", "FRUSTUM_ROOT", "CameraFrusta", "CameraRefinementSource", "DisplayText", "RefinementStatus",
    "S2CampViewerPanel",
]  # fmt: skip
