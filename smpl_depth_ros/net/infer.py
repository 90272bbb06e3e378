"""Run-time correspondence: the trained network + template-embedding lookup (no ROS)."""
from __future__ import annotations

import os
from importlib import resources

import numpy as np
import torch

from smpl_depth_ros.body.parts import MIRROR, PART_COLORS, EmbeddingIndex, template_embedding
from smpl_depth_ros.config import PRECISIONS
from smpl_depth_ros.net.unet import IN_CHANNELS, INPUT_SIZE, build_network


def default_weights(backend: str, kind: str = 'double') -> str:
    return str(resources.files('smpl_depth_ros') / 'data' / f'corr_{backend}_{kind}.pt')


def bfloat16_units() -> bool:
    """Whether this CPU multiplies bfloat16 in hardware: AMX tiles (Intel Xeon of 2023
    on: the network about twice as fast in bfloat16) or AVX-512 BF16 dot products (AMD
    Zen 4 on, Intel Cooper Lake: about 1.6 times); elsewhere bfloat16 is emulated and
    slower than float32."""
    for name in ('_is_amx_tile_supported', '_is_avx512_bf16_supported'):
        probe = getattr(torch.cpu, name, None)
        try:
            if probe is not None and probe():
                return True
        except Exception:  # noqa: BLE001 - an unknown CPU: float32
            pass
    return False


def resolve_precision(precision: str, device: torch.device) -> torch.dtype:
    """The network's arithmetic: 'float32', 'bfloat16', or 'auto' (bfloat16 on a CPU with
    `bfloat16_units`, float32 otherwise, CUDA included)."""
    if precision not in PRECISIONS:
        raise ValueError(f'net_precision must be one of {PRECISIONS}, not {precision!r}')
    if precision == 'auto':
        return torch.bfloat16 if device.type == 'cpu' and bfloat16_units() else torch.float32
    return torch.bfloat16 if precision == 'bfloat16' else torch.float32


def broad_weights(backend: str) -> str | None:
    """The second shipped double U-Net of a backend, trained on every sensor class
    (synth.sensors noise, any resolution) and the broad poses (docs/TRAINING.md); None
    when the backend has none (SMPL: the user trains their own)."""
    path = default_weights(backend, 'double_broad')
    return path if os.path.exists(path) else None


class CorrespondenceNet:
    """Loads the shipped (or given) weights once; maps crops to vertex correspondences.

    Args:
        body: the body model the weights were trained for.
        weights: path to a .pt written by train_correspondence ('' = shipped default).
        device: torch device.
        color_weight: weight of the part colour in the Eq. 2 lookup (>1 keeps matches
            inside the predicted part).
        flip_tta: also run every crop mirrored and average the two predictions (the
            mirrored one with left/right parts swapped and the canonical x mirrored back):
            twice the network time, better segmentation and correspondences.
        precision: the network's arithmetic (`resolve_precision`): with bfloat16 the
            convolutions run in it (autocast: softmax and the outputs stay float32); on 50
            crops of three validation bags 99.8 % of the labels are those of float32 and
            the coordinates move by 0.002 (median; the network's own error is ~0.07).
    """

    def __init__(self, body, weights: str = '', device='cpu', color_weight: float = 2.0,
                 flip_tta: bool = False, precision: str = 'float32'):
        self.flip_tta = flip_tta
        path = weights or default_weights(body.name)
        if not os.path.exists(path):
            raise FileNotFoundError(
                f'no correspondence weights at {path}: for the {body.name!r} backend train '
                f'them with `train_correspondence --backend {body.name} --out {path}` '
                '(see README), or pass weights_path')
        ck = torch.load(path, map_location='cpu', weights_only=True)
        meta = ck.get('meta', {})
        if meta.get('body_vertices') not in (None, body.num_vertices):
            raise ValueError(f'weights {path} were trained for a body with '
                             f'{meta.get("body_vertices")} vertices, this {body.name} model '
                             f'has {body.num_vertices}')
        self.meta = meta
        self.path = path
        # The layers' random initialisation, replaced by the weights, leaves torch's
        # global random stream as it was (building a Reconstructor draws no numbers).
        with torch.random.fork_rng(devices=[]):
            self.net = build_network(meta.get('kind', 'double'))
        self.net.load_state_dict({k: v.float() for k, v in ck['state_dict'].items()})
        self.net.eval().to(device)
        self.device = torch.device(device)
        self.set_precision(precision)
        parts = body.part_labels.cpu().numpy()
        self.embedding = template_embedding(body.canonical_vertices(), parts)
        self.index = EmbeddingIndex(self.embedding, body.valid_vertices.cpu().numpy(),
                                    color_weight=color_weight)

    def set_precision(self, precision: str) -> None:
        """Run in `precision` from now on (see the class); `dtype` says which."""
        self.dtype = resolve_precision(precision, self.device)
        if self.device.type == 'cpu':
            self._run = self._compile(self.net, self.dtype)
        else:
            self._run = self.net

    @staticmethod
    @torch.inference_mode()
    def _compile(net, dtype: torch.dtype = torch.float32):
        """CPU inference: channels-last layout and a frozen TorchScript trace (oneDNN
        convolution fusions), ~30 % faster than eager on this CPU; same outputs to 1e-5.
        With bfloat16 traced under autocast (the casts are part of the trace). Falls back
        to the eager module if tracing fails."""
        net = net.to(memory_format=torch.channels_last)
        x = torch.zeros(1, IN_CHANNELS, INPUT_SIZE, INPUT_SIZE).contiguous(
            memory_format=torch.channels_last)
        try:
            with torch.autocast('cpu', dtype=torch.bfloat16,
                                enabled=dtype == torch.bfloat16):
                return torch.jit.freeze(torch.jit.trace(net, x, check_trace=False))
        except Exception:  # noqa: BLE001 - speed only
            return net

    def _forward(self, t: torch.Tensor):
        """The network's two outputs for the input batch `t`, in `dtype`'s arithmetic."""
        if isinstance(self._run, torch.jit.ScriptModule) or self.dtype == torch.float32:
            return self._run(t)
        with torch.autocast(self.device.type, dtype=self.dtype):
            return self._run(t)

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(x)).to(self.device)
        return t.contiguous(memory_format=torch.channels_last) if self.device.type == 'cpu' \
            else t

    @staticmethod
    def _unmirror(probs: torch.Tensor, coords: torch.Tensor):
        """Outputs of mirrored crops mapped back: flipped, left/right parts swapped (MIRROR
        is its own inverse), canonical x mirrored (the template is left/right symmetric)."""
        probs = probs.flip(-1)[:, torch.as_tensor(MIRROR, device=probs.device)]
        coords = coords.flip(-1)
        return probs, torch.cat([1.0 - coords[:, :1], coords[:, 1:]], 1)

    @torch.inference_mode()
    def raw(self, x: np.ndarray, mirrored: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """One network pass: (B, 2, S, S) inputs -> class probabilities (B, 15, S, S) and
        coords (B, 3, S, S), float32. With `mirrored` the crops are run mirrored and the
        outputs mapped back. `combine` averages passes."""
        t = self._tensor(x[..., ::-1] if mirrored else x)
        logits, coords = self._forward(t)
        probs, coords = logits.float().softmax(1), coords.float()
        if mirrored:
            probs, coords = self._unmirror(probs, coords)
        return probs.cpu().numpy(), coords.cpu().numpy()

    @staticmethod
    def combine(*raws) -> tuple[np.ndarray, np.ndarray]:
        """Average `raw` outputs (plain and mirrored) -> labels (B, S, S) uint8, coords."""
        probs = sum(r[0] for r in raws)
        coords = sum(r[1] for r in raws) / len(raws)
        return probs.argmax(1).astype(np.uint8), coords.astype(np.float32, copy=False)

    @torch.inference_mode()
    def predict(self, x: np.ndarray, flip_tta: bool | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """(B, 2, S, S) inputs -> labels (B, S, S) uint8, coords (B, 3, S, S) float32;
        with flip_tta (default: the constructor's) the plain and the mirrored pass (one
        batch) are averaged, as `combine(raw(x), raw(x, mirrored=True))`."""
        tta = self.flip_tta if flip_tta is None else flip_tta
        B = x.shape[0]
        t = self._tensor(np.concatenate([x, x[..., ::-1]]) if tta else x)
        logits, coords = self._forward(t)
        logits, coords = logits.float(), coords.float()
        if tta:
            pm, cm = self._unmirror(logits[B:].softmax(1), coords[B:])
            logits = logits[:B].softmax(1) + pm
            coords = 0.5 * (coords[:B] + cm)
        return (logits.argmax(1).to(torch.uint8).cpu().numpy(),
                coords.cpu().numpy())

    def lookup(self, labels: np.ndarray, coords: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Eq. 2 for the masked pixels of one crop: vertex ids (N,)."""
        emb = np.concatenate([coords[:, mask].T, PART_COLORS[labels[mask]]], 1)
        return self.index.query(emb)[0]
