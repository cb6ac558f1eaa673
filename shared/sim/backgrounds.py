"""Procedural backgrounds (float32 images in [0, 1]): value noise, clutter and gratings, used behind
the synthetic training tags and as the demo scene's wall textures. numpy and OpenCV only."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

Image = NDArray[Any]


def _value_noise(rng: np.random.Generator, h: int, w: int) -> Image:
    out = np.zeros((h, w), np.float32)
    total = 0.0
    for octave in range(int(rng.integers(2, 6))):
        cell = max(2, int(rng.uniform(8, 200) / (2**octave)))
        small = rng.random((h // cell + 2, w // cell + 2)).astype(np.float32)
        amp = 0.55**octave
        out += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
    return out / total


def _clutter(rng: np.random.Generator, h: int, w: int) -> Image:
    img = np.full((h, w), rng.uniform(0.1, 0.9), np.float32)
    scale = max(h, w)
    for _ in range(int(rng.integers(5, 40))):
        val = float(rng.uniform(0, 1))
        kind = rng.integers(0, 3)
        x, y = int(rng.integers(-w // 4, w)), int(rng.integers(-h // 4, h))
        s = int(rng.uniform(0.03, 0.4) * scale) + 1
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + s, y + int(s * rng.uniform(0.2, 2))), val, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), s // 2, val, -1, lineType=cv2.LINE_AA)
        else:
            x2, y2 = int(rng.integers(0, w)), int(rng.integers(0, h))
            cv2.line(img, (x, y), (x2, y2), val, int(rng.integers(1, 6)), lineType=cv2.LINE_AA)
    return img


def _grating(rng: np.random.Generator, h: int, w: int) -> Image:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    theta = rng.uniform(0, np.pi)
    period = rng.uniform(4, 80)
    phase = (xx * math.cos(theta) + yy * math.sin(theta)) * (2 * np.pi / period)
    wave = np.sin(phase) if rng.random() < 0.5 else np.sign(np.sin(phase))
    return (0.5 + 0.5 * rng.uniform(0.2, 1.0) * wave).astype(np.float32)


def procedural_background(rng: np.random.Generator, h: int, w: int) -> Image:
    """A random mix of value noise, geometric clutter and gratings (nothing downloaded)."""
    makers = [_value_noise, _clutter, _grating]
    first = makers[int(rng.integers(0, 3))](rng, h, w)
    if rng.random() < 0.5:
        second = makers[int(rng.integers(0, 3))](rng, h, w)
        a = float(rng.uniform(0.2, 0.8))
        first = a * first + (1 - a) * second
    lo, hi = sorted(rng.uniform(0, 1, 2))
    return (lo + (hi - lo + 0.05) * first).astype(np.float32)
