# SPDX-License-Identifier: Apache-2.0
"""Render a scene to a file with its ground truth and print a summary.

    python -m ae_tactile.sim.cli config/scenes/single_touch.yaml -o out.npz [--duration S]
        [--seed N] [--chunk-samples N] [--float32]

The .npz holds (np.load(...)):
  samples        (4, N) ADC codes (int16) when quantization is on, else volts (float32,
                 or float64 with --float64); written chunk by chunk, never held whole
  lsb_v          volts per code (samples * lsb_v = volts); 1.0 for volt samples
  sample_rate_hz, start_time_ns (0), channel_xi_eta (4, 2)
  truth_*        per-emission ground truth (EmissionList fields; truth_kind indexes
                 truth_kind_names)
  scene_yaml     the validated scene spec as YAML text; scene_truth_yaml the scene truth
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import zipfile

import numpy as np
import yaml

from ae_tactile.geometry import CHANNEL_XI_ETA
from ae_tactile.sim.scene import CLI_BUDGET, Budget, SceneCost, SceneError, load_scene
from ae_tactile.sim.stream import KINDS, EmissionList


def _write_npy_header(fh, shape, dtype, fortran):
    np.lib.format.write_array_header_1_0(
        fh, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": fortran,
             "shape": tuple(shape)})


def render_to_npz(scene, path, *, chunk_samples=1_000_000, sample_dtype=None, progress=None,
                  budget=CLI_BUDGET):
    """Stream ``scene`` into ``path`` (npz); returns a summary dict.

    The estimated file size must fit ``budget.max_output_bytes`` (SceneError before
    anything is written). The file is written under a temporary name in the same
    directory and renamed when complete: a failed render leaves no partial output."""
    cfg = scene.config
    n_total = scene.n_samples
    if sample_dtype is None:
        sample_dtype = np.int16 if cfg.quantization and cfg.adc_bits <= 16 else np.float32
    chunk_samples = int(chunk_samples)
    if chunk_samples < 1:
        raise ValueError(f"chunk_samples must be >= 1, got {chunk_samples}")
    if budget is not None and budget.max_output_bytes is not None:
        n_em = scene.cost.n_emissions if scene.cost is not None else 0.0
        size = 4.0 * n_total * np.dtype(sample_dtype).itemsize + 81.0 * n_em
        SceneCost(n_em, n_total, 0.0, size).check(Budget(None, budget.max_output_bytes))
    final = os.fspath(path)
    tmp = os.path.join(os.path.dirname(os.path.abspath(final)),
                       f".{os.path.basename(final)}.part{os.getpid()}")
    try:
        summary = _render_npz(scene, tmp, chunk_samples, sample_dtype, progress)
        os.replace(tmp, final)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    summary["path"] = str(path)
    return summary


def _render_npz(scene, path, chunk_samples, sample_dtype, progress):
    cfg = scene.config
    n_total = scene.n_samples
    src = scene.streaming_source()
    truths = []
    clipped = 0
    t0 = time.perf_counter()
    buf = np.empty((4, min(chunk_samples, max(n_total, 1))))
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        with zf.open("samples.npy", "w", force_zip64=True) as fh:
            # (4, N) in Fortran order = sample-interleaved bytes: chunks append in time order
            _write_npy_header(fh, (4, n_total), sample_dtype, True)
            pos = 0
            while pos < n_total:
                n = min(chunk_samples, n_total - pos)
                out = buf[:, :n] if n == buf.shape[1] else np.empty((4, n))
                c = src.next_chunk(n, out=out if out.flags.c_contiguous else None)
                x = c.samples_v
                if np.issubdtype(np.dtype(sample_dtype), np.integer):
                    x = np.rint(x / cfg.lsb_v)
                fh.write(np.ascontiguousarray(x.T, dtype=sample_dtype).tobytes())
                truths.append(c.emissions)
                clipped += int(c.clipped)
                pos += n
                if progress:
                    progress(pos, n_total)
        elapsed = time.perf_counter() - t0
        truth = EmissionList.concat(truths)
        lsb = cfg.lsb_v if np.issubdtype(np.dtype(sample_dtype), np.integer) else 1.0
        extra = {"lsb_v": np.float64(lsb), "sample_rate_hz": np.float64(cfg.sample_rate_hz),
                 "start_time_ns": np.int64(0), "channel_xi_eta": CHANNEL_XI_ETA,
                 "noise_rms_v": np.float64(scene.noise_rms_v),
                 "scene_yaml": np.array(yaml.safe_dump(scene.spec, sort_keys=False)),
                 "scene_truth_yaml": np.array(yaml.safe_dump(_plain(scene.truth),
                                                             sort_keys=False)),
                 **truth.as_arrays()}
        for k, v in extra.items():
            with zf.open(k + ".npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(v), allow_pickle=False)
    return {"path": str(path), "n_samples": n_total, "duration_s": scene.duration_s,
            "elapsed_s": elapsed,
            "realtime_factor": scene.duration_s / elapsed if elapsed > 0 else float("inf"),
            "n_emissions": len(truth),
            "by_type": {k: int(np.sum(truth.kind == i)) for i, k in enumerate(KINDS)
                        if np.any(truth.kind == i)},
            "clipped_chunks": clipped, "scene_truth": _plain(scene.truth),
            "noise_rms_v": scene.noise_rms_v,
            "sample_dtype": np.dtype(sample_dtype).name}


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ae_tactile.sim.cli",
                                 description="Render a simulated-fingertip scene to an .npz file.")
    ap.add_argument("scene", help="scene YAML file (see config/scenes/)")
    ap.add_argument("-o", "--output", required=True, help="output .npz path")
    ap.add_argument("--duration", type=float, default=None, help="override duration_s (s)")
    ap.add_argument("--seed", type=int, default=None, help="override the scene seed")
    ap.add_argument("--chunk-samples", type=int, default=1_000_000,
                    help="samples per rendered chunk")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--float32", action="store_true",
                   help="store volts as float32 even when quantizing")
    g.add_argument("--float64", action="store_true", help="store volts as float64")
    ap.add_argument("--max-memory-gib", type=float, default=CLI_BUDGET.max_memory_bytes / 2 ** 30,
                    help="refuse scenes estimated to need more memory (GiB; default %(default)g)")
    ap.add_argument("--max-output-gib", type=float, default=CLI_BUDGET.max_output_bytes / 2 ** 30,
                    help="refuse outputs estimated larger than this (GiB; default %(default)g)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    dtype = np.float32 if args.float32 else (np.float64 if args.float64 else None)
    try:
        for name in ("max_memory_gib", "max_output_gib"):
            v = getattr(args, name)
            if not (np.isfinite(v) and v > 0):
                raise SceneError(f"--{name.replace('_', '-')} must be a positive number, got {v}")
        if args.chunk_samples < 1:
            raise SceneError(f"--chunk-samples must be >= 1, got {args.chunk_samples}")
        budget = Budget(int(args.max_memory_gib * 2 ** 30), int(args.max_output_gib * 2 ** 30))
        scene = load_scene(args.scene, overrides={"duration_s": args.duration, "seed": args.seed},
                           budget=budget)
        s = render_to_npz(scene, args.output, chunk_samples=args.chunk_samples,
                          sample_dtype=dtype, budget=budget)
    except (SceneError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not args.quiet:
        cfg = scene.config
        print(f"scene      {scene.name} (generator {scene.generator}, seed {scene.seed})")
        print(f"sensor     {cfg.medium}, R = {cfg.geometry.radius_m * 1e3:g} mm, a = "
              f"{cfg.geometry.element_offset_m * 1e3:g} mm, "
              f"c = {cfg.geometry.sound_speed_m_s:g} m/s, "
              f"{cfg.sample_rate_hz / 1e6:g} MS/s, {cfg.adc_bits} bit")
        on = [k for k in ("attenuation", "reflections", "quantization", "release_emissions")
              if scene.effects[k]]
        print(f"effects    {', '.join(on) or 'none'}; noise rms {s['noise_rms_v'] * 1e3:.4g} mV")
        print(f"rendered   {s['n_samples']} samples x 4 ch ({s['duration_s']:g} s)"
              f" in {s['elapsed_s']:.2f} s"
              f" ({s['realtime_factor']:.2f}x real time), stored as {s['sample_dtype']}")
        print(f"emissions  {s['n_emissions']} "
              + ", ".join(f"{k}: {v}" for k, v in s["by_type"].items()))
        if s["clipped_chunks"]:
            print(f"warning    {s['clipped_chunks']} chunk(s) clipped at ADC full scale")
        st = {k: v for k, v in s["scene_truth"].items() if k != "generator"}
        if st:
            print("truth      " + ", ".join(f"{k}={v}" for k, v in st.items()))
        print(f"output     {s['path']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
