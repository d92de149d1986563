"""Neural surrogate perception score model (Sec. "Neural Surrogate Perception Score Models", Alg. 2 line 4).

The surrogate maps the pose of the target relative to the camera, plus a one-hot encoding of the target's class,
to the expected perception score :math:`c_p \\in [0, 1]` (e.g. a detector's confidence):
:math:`c_p(q) \\gets \\mathrm{NN}(T_c, \\mathcal{O})`.

Architecture (as in the paper): an MLP with five fully connected hidden layers of 256 units, ReLU activations and a
sigmoid output.

Inputs
------
* **Relative pose (9)** -- :func:`relative_pose_features`: the target pose in the camera's *optical* frame,
  :math:`T_{ct} = T_c^{-1} T_t`: translation (3) and the continuous 6-D rotation representation (the first two columns
  of :math:`R_{ct}`, Zhou et al. 2019). The rotation matters: the target's +x axis is the direction it faces.
* **Derived features (5, optional, on by default)** -- :func:`derived_features`, deterministic functions of the 9
  pose features that make the main factors of detectability explicit for the MLP:
  ``distance`` :math:`\\|t\\|`, ``bearing_cos`` (cosine between the optical axis and the direction to the target),
  ``facing_cos`` (cosine between the target's facing direction and the direction from the target to the camera),
  and the normalised image coordinates ``image_u = t_x / t_z``, ``image_v = t_y / t_z`` (clamped to [-4, 4]; where the
  target appears in the image, i.e. how close it is to being cut off). They do not change the architecture (only
  the width of the first layer) and can be switched off with ``derived=False`` for the paper's plain inputs.
* **Class (C)** -- one-hot over the ``classes`` the model was trained on (stored with the model).

The pose features are normalised per feature with a mean/std stored as buffers (saved in the state dict); the
one-hot part is not normalised.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
from torch import nn

from ..errors import InputError, OutOfRangeError, UnknownNameError
from ..kernels._fast_packs import MlpPack
from ..kernels.compute import Computing

log = logging.getLogger(__name__)

#: Names of the 9 relative-pose features.
POSE_FEATURE_NAMES = ("tx", "ty", "tz", "r00", "r10", "r20", "r01", "r11", "r21")
#: Names of the optional derived features.
DERIVED_FEATURE_NAMES = ("distance", "bearing_cos", "facing_cos", "image_u", "image_v")
CHECKPOINT_FORMAT = "psprm-perception-surrogate"
CHECKPOINT_VERSION = 1
#: Rows per forward pass on the CPU (keeps activations in cache; ~2x faster than one 65k-row pass on 2 cores).
CPU_CHUNK = 4096

TensorLike = Union[torch.Tensor, np.ndarray, Sequence]


# ------------------------------------------------------------------------------------------------------------------
# Features
# ------------------------------------------------------------------------------------------------------------------
def target_pose_matrix(target) -> np.ndarray:
    """4x4 pose of a :class:`~psprm_core.scene.Target` (or Box) in the scene frame."""
    t = np.eye(4)
    t[:3, :3] = np.asarray(target.rotation, float)
    t[:3, 3] = np.asarray(target.center, float)
    return t


def _as_float_tensor(x: TensorLike, like: Optional[torch.Tensor] = None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x
    else:
        t = torch.as_tensor(np.asarray(x, dtype=float))
    if like is not None:
        t = t.to(device=like.device, dtype=like.dtype)
    elif not t.is_floating_point():
        t = t.double()
    return t


def relative_pose_features(camera_poses: TensorLike, target_pose: TensorLike) -> torch.Tensor:
    """Pose of the target in each camera's optical frame as 9 features (translation + 6-D rotation).

    Parameters
    ----------
    camera_poses : (B, 4, 4) or (4, 4)
        Optical-frame poses in the scene frame (+z forward, +x right, +y down).
    target_pose : (4, 4) or (B, 4, 4), or a Target
        Target pose(s) in the scene frame (+x = facing direction).

    Returns
    -------
    (B, 9) tensor ``[t_x, t_y, t_z, R[:, 0], R[:, 1]]`` of :math:`T_c^{-1} T_t`, on the device and in the dtype of
    ``camera_poses``.
    """
    cam = _as_float_tensor(camera_poses)
    if cam.dim() == 2:
        cam = cam.unsqueeze(0)
    if cam.shape[-2:] != (4, 4):
        raise InputError(f"camera_poses must be (B, 4, 4), got {tuple(cam.shape)}")
    if hasattr(target_pose, "rotation") and hasattr(target_pose, "center"):  # a Target or Box
        target_pose = target_pose_matrix(target_pose)
    tgt = _as_float_tensor(target_pose, like=cam)
    if tgt.shape[-2:] != (4, 4) or tgt.dim() not in (2, 3):
        raise InputError(f"target_pose must be (4, 4) or (B, 4, 4), got {tuple(tgt.shape)}")
    b = cam.shape[0]
    r_c = cam[:, :3, :3]
    # t = R_c^T (p_t - p_c); R_ct[:, :2] = R_c^T R_t[:, :2]  (elementwise sums / one GEMM: faster than tiny bmm's)
    delta = (tgt[..., :3, 3] - cam[:, :3, 3]).unsqueeze(2)  # (B, 3, 1)
    trans = (r_c * delta).sum(dim=1)  # (B, 3)
    if tgt.dim() == 2:
        rot2 = (r_c.transpose(1, 2).reshape(b * 3, 3) @ tgt[:3, :2]).reshape(b, 3, 2)
    else:
        rot2 = r_c.transpose(1, 2) @ tgt[:, :3, :2]
    return torch.cat([trans, rot2[:, :, 0], rot2[:, :, 1]], dim=1)


def derived_features(rel: torch.Tensor) -> torch.Tensor:
    """Derived features (B, 5) from :func:`relative_pose_features` (see the module docstring)."""
    t = rel[:, :3]
    facing = rel[:, 3:6]  # target +x axis in the camera frame
    dist = t.norm(dim=1).clamp_min(1e-9)
    bearing_cos = t[:, 2] / dist
    facing_cos = -(facing * t).sum(dim=1) / dist
    tz = t[:, 2].clamp_min(1e-3)
    u = (t[:, 0] / tz).clamp(-4.0, 4.0)
    v = (t[:, 1] / tz).clamp(-4.0, 4.0)
    return torch.stack([dist, bearing_cos, facing_cos, u, v], dim=1)


def pose_features(camera_poses: TensorLike, target_pose: TensorLike, derived: bool = True) -> torch.Tensor:
    """The surrogate's (un-normalised) pose features: 9 relative-pose features, plus 5 derived ones if ``derived``."""
    rel = relative_pose_features(camera_poses, target_pose)
    return torch.cat([rel, derived_features(rel)], dim=1) if derived else rel


# ------------------------------------------------------------------------------------------------------------------
# Model
# ------------------------------------------------------------------------------------------------------------------
def _plain(x: Any) -> Any:
    """Convert metadata to plain Python types (loadable with ``torch.load(weights_only=True)``)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, torch.Tensor):
        return _plain(x.detach().cpu().tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    if x is None or isinstance(x, (bool, int, float, str)):
        return x
    return repr(x)


class PerceptionSurrogate(Computing, nn.Module):
    """MLP perception score surrogate (paper: 5 hidden layers x 256, ReLU, sigmoid output).

    Parameters
    ----------
    classes : sequence of str
        Object classes of the one-hot encoding, in order (e.g. ``["cup", "face"]``).
    derived : bool
        Whether the 5 derived features are appended to the 9 relative-pose features (see module docstring).
    hidden : int
        Units per hidden layer (paper: 256).
    layers : int
        Number of hidden layers (paper: 5).
    metadata : dict, optional
        Plain-type metadata kept with the model and saved in checkpoints (training config, dataset hash, metrics).

    Notes
    -----
    ``forward`` takes *un-normalised* pose features (B, F) and class indices (B,) and returns scores (B,) in [0, 1];
    :meth:`predict` goes straight from camera poses. The network runs on the device of its parameters; move the model
    with ``.to(device)``.
    """

    def __init__(self, classes: Sequence[str], derived: bool = True, hidden: int = 256, layers: int = 5,
                 metadata: Optional[dict] = None) -> None:
        super().__init__()
        if not classes:
            raise InputError("the surrogate needs at least one class")
        if len(set(classes)) != len(classes):
            raise InputError(f"duplicate classes: {list(classes)}")
        self.classes = [str(c) for c in classes]
        self.derived = bool(derived)
        self.hidden = int(hidden)
        self.layers = int(layers)
        self.metadata: dict = _plain(metadata or {})
        n_feat = self.n_pose_features
        self.register_buffer("feature_mean", torch.zeros(n_feat))
        self.register_buffer("feature_std", torch.ones(n_feat))
        mods: list = []
        width = n_feat + len(self.classes)
        for _ in range(self.layers):
            mods += [nn.Linear(width, self.hidden), nn.ReLU(inplace=True)]
            width = self.hidden
        mods.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*mods)

    # ---- properties ----------------------------------------------------------------------------------------------
    @property
    def n_pose_features(self) -> int:
        return len(POSE_FEATURE_NAMES) + (len(DERIVED_FEATURE_NAMES) if self.derived else 0)

    @property
    def feature_names(self) -> list:
        return list(POSE_FEATURE_NAMES) + (list(DERIVED_FEATURE_NAMES) if self.derived else [])

    @property
    def n_inputs(self) -> int:
        return self.n_pose_features + len(self.classes)

    @property
    def device(self) -> torch.device:
        return self.feature_mean.device

    def class_index(self, name: Union[str, int]) -> int:
        if isinstance(name, (int, np.integer)):
            if not 0 <= int(name) < len(self.classes):
                raise OutOfRangeError(f"class index {name} out of range for {len(self.classes)} classes")
            return int(name)
        try:
            return self.classes.index(str(name))
        except ValueError:
            raise UnknownNameError(f"surrogate was not trained on class '{name}' "
                           f"(classes: {', '.join(self.classes)})") from None

    # ---- normalisation -------------------------------------------------------------------------------------------
    @torch.no_grad()
    def fit_normalization(self, features: torch.Tensor) -> None:
        """Set the per-feature mean/std buffers from un-normalised training features (N, F)."""
        f = torch.as_tensor(features, dtype=torch.float64)
        if f.shape[1] != self.n_pose_features:
            raise InputError(f"expected {self.n_pose_features} features, got {f.shape[1]}")
        self.feature_mean.copy_(f.mean(0).to(self.feature_mean))
        self.feature_std.copy_(f.std(0).clamp_min(1e-6).to(self.feature_std))

    def normalize(self, features: torch.Tensor) -> torch.Tensor:
        return (features - self.feature_mean) / self.feature_std

    def denormalize(self, features: torch.Tensor) -> torch.Tensor:
        return features * self.feature_std + self.feature_mean

    # ---- forward -------------------------------------------------------------------------------------------------
    def encode(self, features: torch.Tensor, class_idx: Union[torch.Tensor, int]) -> torch.Tensor:
        """Network input (B, F + C): normalised pose features and the one-hot class."""
        x = self.normalize(features.to(self.feature_mean.dtype))
        if isinstance(class_idx, torch.Tensor) and class_idx.dim() > 0:
            idx = class_idx.to(device=x.device, dtype=torch.long)
            onehot = nn.functional.one_hot(idx, len(self.classes)).to(x.dtype)
        else:
            onehot = torch.zeros(x.shape[0], len(self.classes), dtype=x.dtype, device=x.device)
            onehot[:, int(class_idx)] = 1
        return torch.cat([x, onehot], dim=1)

    def forward_logits(self, features: torch.Tensor, class_idx: Union[torch.Tensor, int]) -> torch.Tensor:
        """Pre-sigmoid outputs (B,) (use with ``BCEWithLogitsLoss``)."""
        return self.net(self.encode(features, class_idx)).squeeze(-1)

    def forward(self, features: torch.Tensor, class_idx: Union[torch.Tensor, int]) -> torch.Tensor:
        """Scores (B,) in [0, 1] from un-normalised pose features (B, F) and class indices (B,) or one index."""
        return torch.sigmoid(self.forward_logits(features, class_idx))

    def _class_arg(self, class_name, n: int) -> Union[int, torch.Tensor]:
        if isinstance(class_name, (str, int, np.integer)):
            return self.class_index(class_name)
        if isinstance(class_name, torch.Tensor):
            return class_name.to(device=self.device, dtype=torch.long)
        idx = torch.as_tensor([self.class_index(c) for c in class_name], dtype=torch.long, device=self.device)
        if idx.shape[0] != n:
            raise InputError(f"got {idx.shape[0]} class names for {n} camera poses")
        return idx

    @torch.no_grad()
    def predict(self, camera_poses: TensorLike, target_pose: TensorLike,
                class_name: Union[str, int, Sequence, torch.Tensor], chunk_size: Optional[int] = None) -> torch.Tensor:
        """Perception scores for a batch of camera poses (Alg. 2, line 4: :math:`c_p \\gets NN(T_c, O)`).

        Parameters
        ----------
        camera_poses : (B, 4, 4)
            Optical-frame poses in the scene frame (tensor on any device, or array).
        target_pose : (4, 4) or (B, 4, 4)
            Target pose(s) in the scene frame.
        class_name : str, int, sequence of str/int (B,) or index tensor (B,)
            Object class(es).
        chunk_size : int, optional
            Rows per forward pass. Default: 4096 on the CPU (cache-friendly), everything at once on a GPU.

        Returns
        -------
        (B,) tensor in [0, 1], on the device of ``camera_poses`` (the network runs on its own device), in the model's
        dtype. Computed under ``torch.no_grad()`` (the result may be modified in place).

        Notes
        -----
        Numerically the same as ``forward`` (up to float rounding) but with the feature normalisation and the
        one-hot class folded into the first layer's weights, which saves several passes over the batch.
        """
        cam = _as_float_tensor(camera_poses)
        out_device = cam.device
        if cam.dim() == 2:
            cam = cam.unsqueeze(0)
        return self.compute.ops.pose_scores(self, cam, target_pose, class_name, chunk_size).to(out_device)

    def pose_scores_torch(self, cam: torch.Tensor, target_pose, class_name, chunk_size: Optional[int]) -> torch.Tensor:
        """:meth:`predict` of camera poses (B, 4, 4) in torch: pose features, then :meth:`predict_features`."""
        return self.predict_features(pose_features(cam, target_pose, self.derived), class_name, chunk_size)

    @torch.no_grad()
    def predict_features(self, features: torch.Tensor, class_name: Union[str, int, Sequence, torch.Tensor],
                         chunk_size: Optional[int] = None) -> torch.Tensor:
        """Scores (B,) from un-normalised pose features (B, F) (see :meth:`predict`), on the model's device."""
        feats = features.to(device=self.device, dtype=self.feature_mean.dtype)
        cls = self._class_arg(class_name, feats.shape[0])
        if chunk_size is None:
            chunk_size = CPU_CHUNK if self.device.type == "cpu" else feats.shape[0]
        chunk_size = max(1, int(chunk_size))
        out = torch.empty(feats.shape[0], dtype=feats.dtype, device=feats.device)
        w1, b1, w1_cls = self._folded_first_layer(cls)
        rest = self.net[2:]
        for s in range(0, feats.shape[0], chunk_size):
            h = torch.addmm(b1, feats[s:s + chunk_size], w1)
            if w1_cls is not None:
                h += w1_cls[cls[s:s + chunk_size]]
            out[s:s + chunk_size] = torch.sigmoid(rest(h.relu_())).squeeze(-1)
        return out

    def _folded_first_layer(self, cls: Union[int, torch.Tensor]) -> tuple:
        """First layer with the normalisation (and a single class's one-hot) folded in, for inference.

        ``W (x - mean) / std + W_c onehot + b = x W'^T + b'``: returns ``(W'^T (F, H), b' (H,), W_c^T (C, H) or None)``
        where ``W_c^T`` is only returned for per-row classes (then gathered per row).
        """
        first = self.net[0]
        n = self.n_pose_features
        w_feat = first.weight[:, :n] / self.feature_std  # (H, F)
        b = first.bias - w_feat @ self.feature_mean
        w_cls = first.weight[:, n:]  # (H, C)
        if isinstance(cls, torch.Tensor) and cls.dim() > 0:
            return w_feat.t().contiguous(), b, w_cls.t().contiguous()
        return w_feat.t().contiguous(), b + w_cls[:, int(cls)], None

    def kernel_layers(self, cls: int) -> tuple:
        """The inference layers of one class index: ``(layers, pack)`` with ``layers`` the (W^T (in, out), b) pairs
        with the feature normalisation and the class's one-hot column folded into the first one
        (:meth:`_folded_first_layer`), and ``pack`` the float32 :class:`~psprm_core.kernels._fast_packs.MlpPack` of the
        compiled MLP (:mod:`psprm_core.kernels.fastpath`), None when the layers are not float32 or the net does not end
        in a single output. Kept on the model until a parameter or buffer changes: in place (the tensors' versions) or
        by new storage (``.to()``, ``load_state_dict``)."""
        cache = self.__dict__.get("_kernel_layers")
        tensors = cache[1] if cache is not None else list(self.parameters()) + list(self.buffers())
        key = (cls,) + tuple((t._version, t.data_ptr()) for t in tensors)
        if cache is None or cache[0] != key:
            with torch.no_grad():
                w1, b1, _ = self._folded_first_layer(cls)
                layers = [(w1, b1)]
                for mod in self.net[2:]:
                    if isinstance(mod, nn.Linear):
                        layers.append((mod.weight.t().contiguous(), mod.bias.detach().clone()))
                pack = None
                if all(w.dtype == torch.float32 for w, _ in layers) and len(layers) >= 2 and \
                        layers[-1][0].shape[1] == 1:
                    hid = layers[1:-1]
                    H = w1.shape[1]
                    pack = MlpPack(w1.numpy(), b1.numpy(),
                                   np.ascontiguousarray(np.stack([w.numpy() for w, _ in hid]) if hid else
                                                        np.zeros((0, H, H), np.float32)),
                                   np.ascontiguousarray(np.stack([b.numpy() for _, b in hid]) if hid else
                                                        np.zeros((0, H), np.float32)),
                                   np.ascontiguousarray(layers[-1][0].numpy()[:, 0]), np.float32(layers[-1][1].item()))
            cache = self.__dict__["_kernel_layers"] = (key, tensors, layers, pack)
        return cache[2], cache[3]

    # ---- checkpoints ---------------------------------------------------------------------------------------------
    def config(self) -> dict:
        return {"classes": list(self.classes), "derived": self.derived, "hidden": self.hidden, "layers": self.layers,
                "feature_names": self.feature_names}

    def checkpoint(self, **metadata: Any) -> dict:
        """Checkpoint content: plain types and tensors only (``torch.load(..., weights_only=True)`` compatible)."""
        meta = dict(self.metadata)
        meta.update(metadata)
        meta = _plain(meta)
        meta["normalization"] = {"mean": _plain(self.feature_mean), "std": _plain(self.feature_std),
                                 "feature_names": self.feature_names}
        state = {k: v.detach().cpu().clone() for k, v in self.state_dict().items()}
        return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "config": self.config(),
                "state_dict": state, "metadata": meta}

    def save(self, path: Union[str, Path], **metadata: Any) -> Path:
        """Save state dict + metadata (classes, normalisation, and e.g. ``training``, ``dataset_hash``, ``metrics``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.checkpoint(**metadata), tmp)
        tmp.replace(path)
        log.info("saved perception surrogate (%s) to %s", ", ".join(self.classes), path)
        return path

    @classmethod
    def from_checkpoint(cls, ckpt: dict) -> "PerceptionSurrogate":
        if ckpt.get("format") != CHECKPOINT_FORMAT:
            raise InputError(f"not a perception surrogate checkpoint (format={ckpt.get('format')!r})")
        if int(ckpt.get("version", 0)) > CHECKPOINT_VERSION:
            raise InputError(f"checkpoint version {ckpt['version']} is newer than supported ({CHECKPOINT_VERSION})")
        cfg = ckpt["config"]
        model = cls(cfg["classes"], derived=cfg["derived"], hidden=cfg["hidden"], layers=cfg["layers"],
                    metadata=ckpt.get("metadata", {}))
        model.load_state_dict(ckpt["state_dict"])
        return model.eval()

    @classmethod
    def load(cls, path: Union[str, Path],
             map_location: Union[str, torch.device, None] = "cpu") -> "PerceptionSurrogate":
        """Load a checkpoint written by :meth:`save` (with ``weights_only=True``)."""
        ckpt = torch.load(Path(path), map_location=map_location, weights_only=True)
        model = cls.from_checkpoint(ckpt)
        if map_location is not None:
            model = model.to(map_location)
        return model


def load_surrogate(path: Union[str, Path], device: Union[str, torch.device, None] = "cpu") -> PerceptionSurrogate:
    """Load a saved :class:`PerceptionSurrogate` onto ``device``."""
    return PerceptionSurrogate.load(path, map_location=device)


def perception_scores(model: PerceptionSurrogate, camera_poses: TensorLike, target_pose: TensorLike,
                      class_name: Union[str, int, Sequence, torch.Tensor], occlusion=None) -> torch.Tensor:
    """Alg. 2 for a batch: surrogate score (line 4), zeroed where ray casting finds the target occluded (lines 5-7).

    Parameters
    ----------
    model : PerceptionSurrogate
    camera_poses : (B, 4, 4)
        Camera (optical-frame) poses from forward kinematics (line 3).
    target_pose, class_name
        See :meth:`PerceptionSurrogate.predict`.
    occlusion : OcclusionChecker, optional
        From :meth:`psprm_core.perception.occlusion.OcclusionChecker.from_scene`; ``None`` skips lines 5-7.

    Returns
    -------
    (B,) tensor on the device of ``camera_poses``.
    """
    scores = model.predict(camera_poses, target_pose, class_name)
    if occlusion is None:
        return scores
    cams = _as_float_tensor(camera_poses)
    if cams.dim() == 2:
        cams = cams.unsqueeze(0)
    return occlusion.apply(scores, cams)
