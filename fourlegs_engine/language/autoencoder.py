"""The per-scene feature autoencoder (LangSplat-style; paper §3.1): 768 -> 128 -> 768.

Encoder 768 -> 512 -> 256 -> 128 (Linear + BatchNorm + ReLU between layers, L2-normalized latent);
decoder 128 -> 256 -> 512 -> 768 (same blocks, L2-normalized output). Loss: L1 + 0.01 * (1 - cos).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Generator, Sequence

import torch
from torch import nn

from ..errors import InputError

NORM_EPS = 1e-8
COSINE_WEIGHT = 0.01


def l2_normalize(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """x / max(|x|, eps) — zero vectors stay zero instead of becoming NaN."""
    return x / x.norm(dim=dim, keepdim=True).clamp_min(NORM_EPS)


def _mlp(dims: Sequence[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(dims) - 2:
            layers += [nn.BatchNorm1d(b), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class FeatureEncoder(nn.Module):
    """(M, D) features -> (M, d) L2-normalized latents."""

    def __init__(self, dims: Sequence[int] = (768, 512, 256, 128)):
        super().__init__()
        self.dims = tuple(int(d) for d in dims)
        self.net = _mlp(self.dims)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return l2_normalize(self.net(x))

    def first_layer(self) -> nn.Linear:
        return self.net[0]

    def after_first_layer(self, h: torch.Tensor) -> torch.Tensor:
        """Finish encoding from the first Linear's output (M, dims[1]) -> (M, d) normalized latents.

        The first layer is affine and the pixel interpolation is a convex combination of crop
        features, so applying the first layer to crop features and interpolating afterwards is exact;
        the teacher computation uses this to skip most of the 768-d work.
        """
        return l2_normalize(self.net[1:](h))


class FeatureDecoder(nn.Module):
    """(M, d) latents -> (M, D) L2-normalized features."""

    def __init__(self, dims: Sequence[int] = (128, 256, 512, 768)):
        super().__init__()
        self.dims = tuple(int(d) for d in dims)
        self.net = _mlp(self.dims)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return l2_normalize(self.net(z))


class FeatureAutoencoder(nn.Module):
    def __init__(self, feature_dim: int = 768, latent_dim: int = 128, hidden: Sequence[int] = (512, 256)):
        super().__init__()
        self.encoder = FeatureEncoder((feature_dim, *hidden, latent_dim))
        self.decoder = FeatureDecoder((latent_dim, *reversed(tuple(hidden)), feature_dim))

    @property
    def feature_dim(self) -> int:
        return self.encoder.dims[0]

    @property
    def latent_dim(self) -> int:
        return self.encoder.dims[-1]

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(M,D) -> (latents (M,d), reconstruction (M,D))."""
        z = self.encoder(x)
        return z, self.decoder(z)


def reconstruction_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L1 + 0.01 * (1 - cosine), averaged over the batch."""
    l1 = (pred - target).abs().mean()
    cos = torch.nn.functional.cosine_similarity(pred, target, dim=-1, eps=NORM_EPS).mean()
    return l1 + COSINE_WEIGHT * (1.0 - cos)


# ------------------------------------------------------------------------------------ training
AE_CHECKPOINT = "language/autoencoder.ckpt.pt"
AE_REPORT = "language/autoencoder.json"
ENCODER_FILE = "language/encoder.pt"
DECODER_FILE = "language/decoder.pt"


@dataclass
class AETrainOptions:
    """Autoencoder training settings (all enter the config hash).

    Training data is a *sample* of per-pixel teacher features: ``samples`` pixels drawn uniformly
    (seeded) over every timestep and every training camera except ``holdout_camera``, each pixel's
    feature interpolated from the stored crop features. ``heldout_samples`` pixels of the held-out
    camera measure reconstruction cosine on a view the autoencoder never saw.

    ``balance``: "directions" draws twice the sample, groups it into :data:`BALANCE_CLUSTERS` k-means
    clusters of feature directions and takes an equal share from each, so that a rare direction (a small
    object's label: under 1 % of the pixels) is trained on as much as the background; a uniform sample
    leaves it to the decoder to map onto a frequent direction (a ball decoded as a person). "auto" is
    "directions" for the annotation-mask encoder and "none" (uniform) for the others; it enters the config
    hash only when it balances.
    """

    epochs: int = 4
    samples: int = 32768
    heldout_samples: int = 4096
    batch_size: int = 1024
    lr: float = 7e-4
    latent_dim: int = 128
    hidden: tuple[int, ...] = (512, 256)
    holdout_camera: int = -1
    seed: int = 0
    balance: str = "auto"

    def check(self, feature_dim: int = 768) -> "AETrainOptions":
        """InputError naming the first value out of range (before anything is read or replaced)."""
        from ..validate import check_memory, check_number
        check_number(self.epochs, "--epochs", low=1, high=100_000, integer=True)
        check_number(self.samples, "--samples", low=2, high=1 << 31, integer=True)
        check_number(self.heldout_samples, "heldout_samples", low=0, high=1 << 31, integer=True)
        check_number(self.batch_size, "--ae-batch-size", low=2, high=1 << 24, integer=True)
        check_number(self.lr, "--lr", low=0, high=1.0, low_open=True)
        check_number(self.latent_dim, "latent_dim", low=1, high=4096, integer=True)
        check_number(self.seed, "--seed", low=0, high=2 ** 32 - 1, integer=True)
        check_number(self.holdout_camera, "--holdout-camera", low=-(1 << 20), high=1 << 20, integer=True)
        check_memory(4.0 * feature_dim * (self.samples + self.heldout_samples), "the training sample", "--samples")
        return self

    def to_dict(self) -> dict[str, Any]:
        """The settings that enter the config hash (``balance`` is added by the training when it balances)."""
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        d.pop("balance")
        return d

    def resolved_balance(self, encoder_name: str) -> str:
        """"directions" or "none" for features of ``encoder_name`` (see the class docstring)."""
        if self.balance not in ("auto", "directions", "none"):
            raise InputError(f"unknown balance {self.balance!r} (auto, directions, none)", field="balance")
        if self.balance == "auto":
            return "directions" if encoder_name == "masks" else "none"
        return self.balance


def train_autoencoder(scene: Any, config: AETrainOptions | None = None, *, overwrite: bool = False,
                      progress: bool = False, stop_after_epoch: int | None = None,
                      timesteps: Sequence[int] | None = None) -> dict[str, Any]:
    """Train the scene's autoencoder (:func:`autoencoder_training` run to its end, or until
    ``stop_after_epoch`` epochs are done: then ``{"stopped_after_epoch": n}``) and return its report."""
    training = autoencoder_training(scene, config, overwrite=overwrite, progress=progress, timesteps=timesteps)
    while True:
        try:
            done, total = next(training)
        except StopIteration as end:
            return end.value
        if stop_after_epoch is not None and stop_after_epoch <= done < total:
            training.close()
            return {"stopped_after_epoch": done}


def autoencoder_training(scene: Any, config: AETrainOptions | None = None, *, overwrite: bool = False,
                         progress: bool = False, timesteps: Sequence[int] | None = None
                         ) -> Generator[tuple[int, int], None, dict[str, Any]]:
    """Train the scene's autoencoder from its extracted features; resumable from per-epoch checkpoints.

    A generator: yields (epochs done, epochs) after each epoch's checkpoint is written (closing it there
    stops the training; a later call resumes from that checkpoint) and returns the report. The training
    sample is drawn once per call, so a caller reporting progress per epoch pays for it once.

    Writes ``language/encoder.pt`` and ``language/decoder.pt`` (state dicts) and
    ``language/autoencoder.json`` (config hash, reconstruction cosine on held-out and training views,
    loss history, and per epoch the held-out reconstruction cosine and the training seconds: what each
    epoch buys and costs). ``timesteps`` restricts the training data to those timesteps (benchmarks on a few timesteps).
    """
    from ..fileio import save_torch_atomic, write_json_atomic
    from .ae_sample import check_features_complete, check_holdout_camera, training_data
    from .extract import feature_store, stored_timesteps
    from .store import config_hash

    config = (config or AETrainOptions()).check()
    root = Path(scene.root)
    store = feature_store(scene)
    config.check(int(store.config["dim"]))
    check_holdout_camera(config, scene.cameras.num_cameras(store.config.get("split", "train")))
    steps = stored_timesteps(scene, store.config) if timesteps is None else sorted({int(t) for t in timesteps})
    check_features_complete(store, steps)
    balance = config.resolved_balance(str(store.config.get("encoder", "")))
    cfg = {"features": store.hash, **config.to_dict(), **({"balance": balance} if balance != "none" else {})}
    if timesteps is not None:
        cfg["timesteps"] = steps
    chash = config_hash(cfg)
    report_path = root / AE_REPORT
    trained = _refuse_or_drop_other_configurations(root, chash, overwrite)
    if trained and not overwrite:
        report = read_ae_report(report_path)
        report["skipped"] = True
        return report

    start = time.perf_counter()
    x_train, x_held, holdout = training_data(scene, store, config, steps, balance)
    sample_seconds = time.perf_counter() - start
    torch.manual_seed(config.seed)
    model = FeatureAutoencoder(int(store.config["dim"]), config.latent_dim, config.hidden)
    x_monitor = x_held if x_held.shape[0] else x_train[:config.heldout_samples]
    history, cosine_history, epoch_seconds = yield from _train_epochs(model, x_train, x_monitor, config, chash,
                                                                      root / AE_CHECKPOINT, progress=progress)
    model.eval()
    _check_trained(model, history)
    report = {"config_hash": chash, "config": cfg, "epochs": config.epochs, "loss_history": history,
              "cosine_history": cosine_history, "cosine_history_set": "heldout" if x_held.shape[0] else "train",
              "epoch_seconds": epoch_seconds,
              "train_samples": int(x_train.shape[0]), "heldout_camera": holdout,
              "heldout_samples": int(x_held.shape[0]),
              "train_cosine": reconstruction_cosine(model, x_train[:config.heldout_samples]),
              "heldout_cosine": reconstruction_cosine(model, x_held) if x_held.shape[0] else None,
              "heldout_note": "" if x_held.shape[0] else (
                  "no camera to hold out (one training camera)" if holdout is None else
                  f"held-out camera {holdout} has no evidence (no camera but those trained on has any)"),
              "sample_seconds": sample_seconds, "balance": balance, "seconds": time.perf_counter() - start,
              "encoder": ENCODER_FILE, "decoder": DECODER_FILE}
    json.dumps(report, allow_nan=False)  # the report must be writable before the weights are replaced
    save_torch_atomic(root / ENCODER_FILE, model.encoder.state_dict())
    save_torch_atomic(root / DECODER_FILE, model.decoder.state_dict())
    write_json_atomic(report_path, report)
    (root / AE_CHECKPOINT).unlink(missing_ok=True)
    return report


def _check_trained(model: nn.Module, history: list[float]) -> None:
    """InputError when training diverged (NaN/Inf loss or weights): nothing is written then."""
    from ..errors import InputError
    finite = all(math.isfinite(v) for v in history) and all(
        bool(torch.isfinite(v).all()) for v in model.state_dict().values() if v.is_floating_point())
    if not finite:
        raise InputError("training diverged (NaN or Inf loss or weights); the previous autoencoder is kept: "
                         "lower --lr", field="--lr")


def _refuse_or_drop_other_configurations(root: Path, chash: str, overwrite: bool) -> bool:
    """ConfigMismatchError for a report or checkpoint of another configuration, unless ``overwrite`` (then
    the checkpoint is removed; the report stays until the new autoencoder replaces it). A checkpoint of
    this configuration is an interrupted run (``--overwrite`` or not) that is resumed. Returns whether the
    report is of this configuration (the autoencoder is trained)."""
    from ..errors import ConfigMismatchError

    report, ckpt = root / AE_REPORT, root / AE_CHECKPOINT
    if ckpt.is_file():
        old = _read_checkpoint(ckpt).get("config_hash")
        if old == chash:
            return False
        if not overwrite:
            raise ConfigMismatchError(f"{ckpt}: an autoencoder of another configuration exists (hash {old}, now "
                                      f"{chash}); pass --overwrite to retrain, or use the same settings")
        ckpt.unlink()
    if not report.is_file():
        return False
    old = read_ae_report(report).get("config_hash")
    if old != chash and not overwrite:
        raise ConfigMismatchError(f"{report}: an autoencoder of another configuration exists (hash {old}, now "
                                  f"{chash}); pass --overwrite to retrain, or use the same settings")
    return old == chash


def read_ae_report(path: Path) -> dict[str, Any]:
    """``autoencoder.json`` as a dict; InputError naming it when it is not a JSON object."""
    from ..errors import InputError
    from ..fileio import read_json
    report = read_json(path)
    if not isinstance(report, dict) or not isinstance(report.get("config_hash", ""), str):
        raise InputError("must be a JSON object with a text config_hash; run `fourlegs train-ae --overwrite`",
                         file=path)
    return report


def _train_epochs(model: FeatureAutoencoder, x_train: torch.Tensor, x_monitor: torch.Tensor, config: AETrainOptions,
                  chash: str, ckpt_path: Path, *, progress: bool
                  ) -> Generator[tuple[int, int], None, tuple[list[float], list[float], list[float]]]:
    """Adam over shuffled batches, resuming from and saving to ``ckpt_path`` after every epoch, then
    yielding (epochs done, epochs).

    Returns per epoch the mean loss, the reconstruction cosine on ``x_monitor`` (what the epochs buy) and
    the training seconds (what they cost).
    """
    from ..fileio import save_torch_atomic

    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    history: list[float] = []
    cosine_history: list[float] = []
    epoch_seconds: list[float] = []
    first_epoch = 0
    if ckpt_path.is_file():
        ckpt = _read_checkpoint(ckpt_path)
        try:
            model.load_state_dict(ckpt["model"])
            opt.load_state_dict(ckpt["optimizer"])
            first_epoch = int(ckpt["epoch"])
            history = [float(v) for v in ckpt["history"]]
            cosine_history = [float(v) for v in ckpt.get("cosine_history", [])]
            epoch_seconds = [float(v) for v in ckpt.get("epoch_seconds", [])]
        except (RuntimeError, ValueError, TypeError, KeyError, AttributeError) as exc:
            from ..errors import InputError
            raise InputError(f"damaged checkpoint ({type(exc).__name__}: {str(exc).splitlines()[0][:120]}); delete "
                             "it or pass --overwrite", file=ckpt_path) from None
        if not 0 <= first_epoch <= config.epochs:
            from ..errors import InputError
            raise InputError(f"epoch {first_epoch} is out of range 0..{config.epochs}; delete it or pass --overwrite",
                             file=ckpt_path, field="epoch")
    epochs = range(first_epoch, config.epochs)
    if progress:
        from tqdm import tqdm
        epochs = tqdm(epochs, desc="train-ae", unit="epoch", initial=first_epoch, total=config.epochs)
    n = x_train.shape[0]
    for epoch in epochs:
        epoch_start = time.perf_counter()
        model.train()
        gen = torch.Generator().manual_seed(config.seed * 100003 + epoch)
        order = torch.randperm(n, generator=gen)
        total, count = 0.0, 0
        for s in range(0, n, config.batch_size):
            idx = order[s:s + config.batch_size]
            if idx.numel() < 2:  # BatchNorm needs two samples
                continue
            batch = x_train[idx]
            _, recon = model(batch)
            loss = reconstruction_loss(recon, batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * idx.numel()
            count += idx.numel()
        history.append(total / max(count, 1))
        _check_trained(model, history)  # a diverged epoch is not checkpointed
        epoch_seconds.append(time.perf_counter() - epoch_start)
        cosine_history.append(reconstruction_cosine(model, x_monitor))
        save_torch_atomic(ckpt_path, {"config_hash": chash, "epoch": epoch + 1, "model": model.state_dict(),
                                      "optimizer": opt.state_dict(), "history": history,
                                      "cosine_history": cosine_history, "epoch_seconds": epoch_seconds})
        yield epoch + 1, config.epochs
    return history, cosine_history, epoch_seconds


def _read_checkpoint(path: Path) -> dict[str, Any]:
    """The training checkpoint (a dict of tensors and numbers), or InputError naming it."""
    import pickle

    from ..errors import InputError
    from ..fileio import TORCH_LOAD_ERRORS, unpickling_detail
    try:
        ckpt = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as exc:
        raise InputError(f"refused: not a plain checkpoint ({unpickling_detail(exc)}); pickled objects are never "
                         "loaded: delete it or pass --overwrite", file=path) from None
    except TORCH_LOAD_ERRORS as exc:
        raise InputError(f"damaged checkpoint ({type(exc).__name__}); delete it or pass --overwrite",
                         file=path) from None
    if not isinstance(ckpt, dict) or not {"model", "optimizer", "epoch", "history"} <= set(ckpt):
        raise InputError("not a training checkpoint of this program; delete it or pass --overwrite", file=path)
    return ckpt


@torch.no_grad()
def reconstruction_cosine(model: FeatureAutoencoder, x: torch.Tensor) -> float:
    """Mean cosine between features and their reconstructions (model in eval mode)."""
    was_training = model.training
    model.eval()
    _, recon = model(x)
    model.train(was_training)
    return float(torch.nn.functional.cosine_similarity(recon, x, dim=-1, eps=NORM_EPS).mean())


def _dims_from_state(state: dict[str, torch.Tensor]) -> tuple[int, ...]:
    """Layer widths of an MLP state dict (net.0.weight, net.3.weight, ...)."""
    weights = sorted(((int(k.split(".")[1]), v) for k, v in state.items()
                      if k.startswith("net.") and k.endswith(".weight") and v.dim() == 2), key=lambda kv: kv[0])
    if not weights:
        raise ValueError("no Linear layers in the state dict")
    return (int(weights[0][1].shape[1]),) + tuple(int(w.shape[0]) for _, w in weights)


def load_encoder(path: str | Path) -> FeatureEncoder:
    """The trained feature encoder (eval mode) from its state dict (never unpickles)."""
    return _load(path, FeatureEncoder)


def load_decoder(path: str | Path) -> FeatureDecoder:
    """The trained feature decoder (eval mode) from its state dict (never unpickles)."""
    return _load(path, FeatureDecoder)


def _load(path: str | Path, cls: type) -> Any:
    import pickle

    from ..errors import InputError
    from ..fileio import TORCH_LOAD_ERRORS, unpickling_detail
    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing; run `fourlegs train-ae` first", file=path)
    try:
        state = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as exc:
        raise InputError(f"refused: holds pickled Python objects or is not a torch file "
                         f"({unpickling_detail(exc)}); pickled objects are never loaded, only tensor state "
                         "dicts: run `fourlegs train-ae --overwrite` to write it again", file=path) from None
    except TORCH_LOAD_ERRORS as exc:
        raise InputError(f"not a readable torch file ({str(exc).splitlines()[0][:200] if str(exc) else exc!r}); "
                         "run `fourlegs train-ae --overwrite` to write it again", file=path) from None
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise InputError(f"not a {cls.__name__} state dict (a mapping of names to tensors; found "
                         f"{type(state).__name__})", file=path)
    try:
        model = cls(_dims_from_state(state))
        model.load_state_dict(state, strict=True)
    except (RuntimeError, ValueError, KeyError, IndexError) as exc:
        raise InputError(f"not a valid {cls.__name__} state dict ({str(exc).splitlines()[0][:200]})",
                         file=path) from None
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise InputError(f"weights {', '.join(bad[:3])} contain NaN or Inf; run `fourlegs train-ae --overwrite`",
                         file=path)
    return model.eval()


def weights_fingerprint(module_or_state: nn.Module | dict[str, torch.Tensor]) -> str:
    """SHA-256 (first 16 hex digits) of a state dict's names, dtypes, shapes and values.

    A language field records the fingerprint of the decoder it was distilled with, so a decoder
    retrained later (``train-ae --overwrite``) is noticed instead of silently decoding old latents.
    """
    import hashlib

    state = module_or_state.state_dict() if isinstance(module_or_state, nn.Module) else module_or_state
    digest = hashlib.sha256()
    for name in sorted(state):
        tensor = state[name].detach().cpu().reshape(-1).contiguous()
        digest.update(f"{name}|{state[name].dtype}|{tuple(state[name].shape)}|".encode())
        digest.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()[:16]
