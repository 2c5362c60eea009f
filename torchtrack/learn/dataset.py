"""The synthetic training set for learned weighting: many rendered variants, each recorded into the observation cache.

A set is a config (conf/dataset/*.yaml, under the key ``dataset``): the product of seeds x scene modes x motion
speeds x noise levels, each one :class:`~torchtrack.data.synthetic.SyntheticConfig` on a common ``base``. Every
variant is rendered once (the renderer's cache, keyed by the config's digest) and recorded with the pipeline of
the composed config (:func:`torchtrack.learn.record.record_sequences`) into ``out_dir/<variant>.pt``, tracked with
the region its mode needs (``regions``: scene -> the whole frame, object -> depth thresholding). Resumable: files
recorded from the same rendered sequence with the same config are kept. ``out_dir/dataset.json`` lists the
variants (file, region, full SyntheticConfig). Missing renders are made by ``render_workers`` processes in parallel.

    torchtrack-record +dataset=synthetic out=DIR        # the default set
    torchtrack-record +dataset=synthetic_tiny out=DIR   # 2 sequences of 6 frames at 160 x 120 (tests)

A noise entry is a sensor model: :class:`~torchtrack.data.synthetic.KinectNoise` parameters and the renderer's
real-sensor effects (``effects``: :class:`~torchtrack.data.synthetic.config.SensorEffects`: misregistration, flying
pixels, motion blur, a lighting gain over time), and optionally ``perturb``: a :mod:`torchtrack.data.perturb` kind
with its parameters applied to the render (e.g. ``{kind: depth_noise, sigma_k: 1.5e-3}``: i.i.d. axial noise growing
with z^2, dropout and hole blobs, on exact rendered depth). The sequences of ``photometric_seeds`` are recorded from
their photometric variant (:mod:`torchtrack.data.perturb`) instead.
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from torchtrack.config import load_option
from torchtrack.data.perturb import make_variant
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence, sequence_name
from torchtrack.data.tum import TumSequence
from torchtrack.io import write_json
from torchtrack.learn.record import record_sequences

log = logging.getLogger("torchtrack.record")


@dataclass
class Variant:
    """One sequence of a synthetic set: its name (the cache file's), renderer config and region config name."""

    name: str
    config: SyntheticConfig
    region: str
    photometric: bool = False  # recorded from the photometric variant of the render (torchtrack.data.perturb)
    perturb: dict | None = None  # {kind, **params}: a torchtrack.data.perturb variant of the render, applied first


def synthetic_variants(spec: DictConfig | dict) -> list[Variant]:
    """Every combination of ``spec``'s seeds, modes, speeds and noises, on ``spec.base``; named
    ``<mode>-<speed>-<noise>-seed<seed>`` after the keys of those maps. A speed gives the steps per renderer mode
    (``speeds.<speed>.<scene|object>``)."""
    spec = OmegaConf.create(spec) if isinstance(spec, dict) else spec
    out = []
    for seed, mode, speed, noise in itertools.product(spec.seeds, spec.modes, spec.speeds, spec.noises):
        kind = spec.modes[mode].get("mode", "scene")
        parts = (spec.base, spec.modes[mode], spec.speeds[speed][kind], spec.noises[noise])
        params = OmegaConf.to_container(OmegaConf.merge(OmegaConf.create(), *parts), resolve=True)
        perturb = params.pop("perturb", None)
        cfg = SyntheticConfig(**params, seed=int(seed))
        photo = int(seed) in set(spec.get("photometric_seeds") or [])
        name = f"{mode}-{speed}-{noise}-seed{seed}" + ("-photometric" if photo else "")
        out.append(Variant(name, cfg, spec.regions[cfg.mode], photo, perturb))
    return out


def render_variants(variants: list[Variant], cache: Path, workers: int = 1, progress: bool = True) -> list[Path]:
    """The rendered folder of every variant (:func:`~torchtrack.data.synthetic.ensure_sequence`: cached, safe
    against concurrent renderers), rendering the missing ones in ``workers`` processes."""
    todo = [v for v in variants if not (cache / sequence_name(v.config) / "SOURCE.txt").is_file()]
    log.info("%d of %d variants to render into %s", len(todo), len(variants), cache)
    if workers > 1 and len(todo) > 1:
        with ProcessPoolExecutor(min(workers, len(todo)), mp_context=multiprocessing.get_context("spawn")) as pool:
            jobs = [pool.submit(ensure_sequence, v.config, cache) for v in todo]
            for job in tqdm(as_completed(jobs), total=len(jobs), desc="rendering", unit="seq", disable=not progress):
                job.result()
    else:
        for v in tqdm(todo, desc="rendering", unit="seq", disable=not progress):
            ensure_sequence(v.config, cache)
    return [ensure_sequence(v.config, cache) for v in variants]


def build_synthetic_set(cfg: DictConfig, out_dir: str | Path, progress: bool = True) -> list[Path]:
    """Render (cached) and record every variant of ``cfg.dataset`` into ``out_dir``; returns the files in variant
    order. ``cfg``: the composed config (conf/config.yaml's groups) whose pipeline records; its ``region`` and
    ``data`` are replaced per variant."""
    spec = cfg.dataset
    out_dir = Path(out_dir)
    variants = synthetic_variants(spec)
    cache, workers = Path(spec.cache_dir).expanduser(), int(spec.get("render_workers") or 1)
    folders = render_variants(variants, cache, workers, progress)
    for i, v in enumerate(variants):  # perturb's photometric walk, beside the renderer's own lighting effect
        if v.perturb:
            p = dict(v.perturb)
            folders[i] = make_variant(folders[i], p.pop("kind"), cache / "perturbed", seed=v.config.seed, **p)
        if v.photometric:
            folders[i] = make_variant(folders[i], "photometric", cache / "perturbed", seed=v.config.seed)
    paths: list[Path | None] = [None] * len(variants)
    for region in dict.fromkeys(v.region for v in variants):
        group = [i for i, v in enumerate(variants) if v.region == region]
        files = record_sequences(
            _with_region(cfg, region), [TumSequence(folders[i], **_rig(variants[i].config)) for i in group], out_dir,
            names=[variants[i].name for i in group], batch=spec.get("batch"), progress=progress,
        )  # fmt: skip
        for i, f in zip(group, files, strict=True):
            paths[i] = f
    index = {
        "name": spec.name,
        "variants": [
            {"name": v.name, "file": p.name, "region": v.region, "synthetic": v.config.to_dict(), "perturb": v.perturb}
            for v, p in zip(variants, paths, strict=True)
        ],
    }
    write_json(out_dir / "dataset.json", index, indent=1)
    return paths


def _rig(config: SyntheticConfig) -> dict:
    """TumSequence's arguments for a render with a depth camera of its own (its intrinsics and extrinsic), else none."""
    cam = config.depth_camera
    if cam is None:
        return {}
    return {"intrinsics_depth": (cam["fx"], cam["fy"], cam["cx"], cam["cy"]), "T_color_depth": cam["T_color_depth"]}


def _with_region(cfg: DictConfig, region: str) -> DictConfig:
    """cfg with conf/region/<region>.yaml as its region, and data naming the set (the sequences come from it)."""
    g = cfg.copy()
    OmegaConf.set_struct(g, False)
    g.region = load_option("region", region)
    g.data = OmegaConf.create({"kind": "synthetic", "set": str(cfg.dataset.name)})
    return g
