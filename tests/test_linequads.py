"""Stage 1's line-quad proposer (shared.vision.linequads; its corner convention is checked with ArUco's in
tests/test_proposals.py): occluded tags
that AprilTag loses, the decode's bit budget, no tags from tag-like squares that are no code word, and
its place in Stage1Detector."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pydantic
import pytest
from numpy.typing import NDArray

from bench.tagrender import RenderSettings, clean_settings, render_sample
from shared.vision.detector import DetectorSettings, TagDetector, quad_side_px
from shared.vision.linequads import LineQuadProposer, LineQuadSettings, _data_book
from shared.vision.proposals import ArucoSettings, Stage1Detector, Stage1Settings
from shared.vision.tags import tag_cells

OCCLUDED = RenderSettings(
    p_occluder=1.0,
    p_motion_blur=0.0,
    p_defocus=0.0,
    p_distractors=0.0,
    span_px=(80.0, 220.0),
    tilt_deg=(0.0, 40.0),
)


def test_a_finger_or_cable_across_the_border_loses_apriltag_not_the_line_quads() -> None:
    """Tags with an occluder across the black border (all four corners in view): AprilTag 3 finds few,
    the line-quad proposer most, every one with its own id and corners within a pixel."""
    proposer, apriltag = LineQuadProposer(), TagDetector(DetectorSettings(quad_decimate=1.0))
    ours = theirs = occluded = 0
    errors = []
    for index in range(12):
        sample = render_sample(index, 5, OCCLUDED)
        truth = sample.tags[0]
        if sample.meta["occluded_fraction"] <= 0.0:
            continue
        occluded += 1
        found = proposer.detect(sample.image)
        assert all(d.tag_id == truth.tag_id for d in found), (sample.meta, [d.tag_id for d in found])
        if found:
            ours += 1
            errors.append(float(np.linalg.norm(found[0].corners_px - truth.corners_px, axis=1).max()))
        theirs += any(d.tag_id == truth.tag_id for d in apriltag.detect(sample.image))
    apriltag.close()
    print(f"\noccluded tags: line quads {ours}/{occluded}, AprilTag 3 (decimate 1) {theirs}/{occluded}")
    assert occluded >= 10
    assert ours >= 0.75 * occluded
    assert theirs <= 0.3 * occluded
    assert float(np.median(errors)) < 1.0, errors


def _draw(data_bits: NDArray[np.bool_] | None, tag_id: int = 0, *, seed: int = 0) -> NDArray[np.uint8]:
    """A 10x10-cell tag (white ring, black ring, 6x6 data) drawn sharp under a mild perspective on a
    grey background: `data_bits` replaces the tag's own 36 bits when given."""
    cells = tag_cells(tag_id).astype(np.float64)
    if data_bits is not None:
        cells[2:-2, 2:-2] = data_bits.reshape(6, 6)
    px = 16
    flat = np.kron(cells, np.ones((px, px))) * 200 + 30
    rng = np.random.default_rng(seed)
    src = np.array([[0, 0], [160, 0], [160, 160], [0, 160]], np.float32)
    dst = src * 1.2 + np.array([120, 80], np.float32) + rng.uniform(-12, 12, (4, 2)).astype(np.float32)
    h = cv2.getPerspectiveTransform(src, dst)
    canvas = np.full((420, 460), 120.0)
    warped = cv2.warpPerspective(flat, h, (460, 420), flags=cv2.INTER_AREA, borderValue=-1.0)
    canvas = np.where(warped >= 0, warped, canvas)
    return np.clip(canvas, 0, 255).astype(np.uint8)


def _flip(bits: NDArray[np.bool_], n: int, seed: int) -> NDArray[np.bool_]:
    out = bits.copy()
    idx = np.random.default_rng(seed).choice(36, n, replace=False)
    out[idx] = ~out[idx]
    return out


def test_the_decode_takes_three_bit_errors_and_refuses_four() -> None:
    """Up to max_hamming (3) flipped data bits still read as the tag's own id; 4 read as nothing (36h11's
    minimum distance 11 keeps every other word >= 7 bits away, so no wrong id either way). The hard
    decode alone: the blind soft decode may read the 4-bit one as its own id (never as another)."""
    proposer = LineQuadProposer(HARD)
    tag_id = 117
    own = tag_cells(tag_id)[2:-2, 2:-2].ravel() > 0
    assert [d.tag_id for d in proposer.detect(_draw(None, tag_id))] == [tag_id]
    for seed in range(4):
        three = proposer.detect(_draw(_flip(own, 3, seed), tag_id, seed=seed))
        assert [(d.tag_id, d.hamming) for d in three] == [(tag_id, 3)]
        assert proposer.detect(_draw(_flip(own, 4, seed), tag_id, seed=seed)) == []


def test_tag_like_squares_that_are_no_code_word_give_no_tag() -> None:
    """Black-bordered squares whose 36 bits are >= 4 bits from every tag36h11 word in every rotation
    are drawn exactly like tags: none is reported (and the same squares with a code word are)."""
    book, _, _ = _data_book()
    rng = np.random.default_rng(7)
    proposer = LineQuadProposer()
    tried = 0
    while tried < 12:
        bits = rng.random(36) < 0.5
        if np.count_nonzero(book != bits[None, :], axis=1).min() < 4:
            continue
        tried += 1
        assert proposer.detect(_draw(bits, seed=tried)) == [], bits
    assert len(proposer.detect(_draw(None, 42, seed=1))) == 1


def test_stage1_adds_what_only_the_line_quads_find_and_counts_it() -> None:
    sample = render_sample(0, 5, OCCLUDED)
    truth = sample.tags[0]
    no_apriltag = DetectorSettings(min_decision_margin=1e9)  # AprilTag finds nothing
    stage1 = Stage1Detector(Stage1Settings(apriltag=no_apriltag, aruco=ArucoSettings(enabled=False)))
    found = stage1.detect(sample.image)
    assert [(d.tag_id, d.proposer) for d in found] == [(truth.tag_id, "lines")]
    assert (stage1.counts.lines_added, stage1.counts.lines_merged) == (1, 0)
    off = Stage1Detector(
        Stage1Settings(apriltag=no_apriltag, aruco=ArucoSettings(enabled=False), lines=LineQuadSettings(enabled=False))
    )
    assert off.detect(sample.image) == []
    both = Stage1Detector(Stage1Settings(aruco=ArucoSettings(enabled=False)))
    clean = render_sample(1, 11, clean_settings(span_px=(100.0, 160.0), tilt_deg=(0.0, 20.0)))
    assert [d.proposer for d in both.detect(clean.image)] == ["apriltag"]  # AprilTag's corners stay
    assert (both.counts.lines_added, both.counts.lines_merged) == (0, 1)
    for d in (stage1, off, both):
        d.close()


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((40, 40, 3), np.uint8), "2-D"),
        (np.zeros((40, 40), np.float32), "uint8"),
        (np.zeros((4, 40), np.uint8), "at least 8x8"),
    ],
)
def test_a_bad_image_is_refused_with_what_it_was(image: NDArray[np.generic], match: str) -> None:
    from shared.vision.geometry import GeometryError

    with pytest.raises(GeometryError, match=match):
        LineQuadProposer().detect(image)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "field", ["scale", "max_hamming", "min_ring_fraction", "soft_min_ring_fraction", "soft_max_per_frame"]
)
def test_out_of_range_settings_are_refused(field: str) -> None:
    bad = {
        "scale": 0.0,
        "max_hamming": 5,
        "min_ring_fraction": 0.5,
        "soft_min_ring_fraction": 0.5,
        "soft_max_per_frame": -1,
    }[field]
    with pytest.raises(pydantic.ValidationError, match=field):
        LineQuadSettings(**{field: bad})


def test_a_tag_the_image_edge_cuts_through_its_white_ring_gives_nothing() -> None:
    """Its white ring would be read from replicated border pixels: the line quads report a tag only when
    the whole tag, white ring included, is in the image."""
    proposer = LineQuadProposer()
    image = _draw(None, 9)
    (whole,) = proposer.detect(image)
    x0 = int(whole.corners_px[:, 0].min()) - 2  # keep the black square, cut the white ring
    assert proposer.detect(np.ascontiguousarray(image[:, x0:])) == []
    x1 = int(whole.corners_px[:, 0].min()) - 40  # the whole tag still in view
    assert [d.tag_id for d in proposer.detect(np.ascontiguousarray(image[:, x1:]))] == [9]


SOFT = LineQuadSettings(soft_decode=True)  # the default, said where a test is about it
HARD = LineQuadSettings(soft_decode=False)  # the hard decode alone
# the occluded renders' settings with the occluder swapped for exposure blur, on smaller tags
SMALL_BLURRED = replace(OCCLUDED, p_occluder=0.0, p_motion_blur=1.0, span_px=(30.0, 60.0))


def test_the_soft_decode_reads_small_tags_that_motion_blur_smeared_past_the_bits() -> None:
    """30-60 px tags under >= 10 px of exposure blur (bench/tagrender, not the project's code): the hard
    decode reads some, the blind soft decode (shared.vision.softdecode) reads more, never a wrong id."""
    soft, hard = LineQuadProposer(SOFT), LineQuadProposer(HARD)
    n = hard_found = soft_found = 0
    for index in range(60):
        sample = render_sample(index, 3, SMALL_BLURRED)
        if sample.meta["blur_px"] < 10.0:
            continue
        n += 1
        tag_id = sample.tags[0].tag_id
        got = soft.detect(sample.image)
        assert all(d.tag_id == tag_id for d in got), (index, [d.tag_id for d in got], tag_id)
        if got:
            truth = sample.tags[0].corners_px
            err = np.linalg.norm(got[0].corners_px - truth, axis=1).max()
            # the right corner order: a wrong rotation would put each corner a side (>= 30 px) away
            assert err < 0.25 * quad_side_px(truth), (index, err)
        soft_found += bool(got)
        hard_found += any(d.tag_id == tag_id for d in hard.detect(sample.image))
    print(f"\n{n} small blurred tags: hard decode {hard_found}, with the soft decode {soft_found}")
    assert n >= 15
    assert soft_found >= hard_found + 3
    assert soft.soft_decoded == soft_found - hard_found


def _blurred(image: NDArray[np.uint8], length_px: float, angle_deg: float) -> NDArray[np.uint8]:
    from shared.vision.blur import line_kernel

    k = line_kernel(length_px, np.radians(angle_deg))
    return np.asarray(cv2.filter2D(image, -1, k, borderType=cv2.BORDER_REPLICATE), np.uint8)


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_the_blind_decode_reads_id_and_orientation_under_blur_it_was_not_told(turns: int) -> None:
    """A tag blurred by 2.5 cells at 30 deg, the quad given in any of its four corner orders: the id is
    read and the corners come back TL, TR, BR, BL of the tag."""
    from shared.vision.softdecode import BlindDecodeSettings, blind_decode

    image = _blurred(_draw(None, 117), 2.5 * 16 * 1.2, 30.0)
    (sharp,) = LineQuadProposer().detect(_draw(None, 117))
    quad = np.roll(sharp.corners_px, turns, axis=0)
    r = blind_decode(image, quad, BlindDecodeSettings())
    assert r is not None and r.accepted, r
    assert r.tag_id == 117
    np.testing.assert_allclose(r.corners_px, sharp.corners_px)
    assert 1.5 < float(np.hypot(*r.blur_cells)) < 3.5, r.blur_cells


def test_blurred_squares_that_are_no_code_word_give_no_tag() -> None:
    """The same squares as above (>= 4 bits from every word), blurred so that no bit reads: the soft
    decode finds no word that fits clearly better than the rest, and the proposer reports nothing."""
    from shared.vision.softdecode import BlindDecodeSettings, blind_decode

    book, _, _ = _data_book()
    rng = np.random.default_rng(8)
    proposer = LineQuadProposer(SOFT)
    (sharp,) = proposer.detect(_draw(None, 42, seed=1))
    tried = 0
    while tried < 10:
        bits = rng.random(36) < 0.5
        if np.count_nonzero(book != bits[None, :], axis=1).min() < 4:
            continue
        tried += 1
        image = _blurred(_draw(bits, seed=1), 20.0, float(rng.uniform(0, 180)))
        assert proposer.detect(image) == [], bits
        r = blind_decode(image, sharp.corners_px, BlindDecodeSettings())
        assert r is None or not r.accepted, r
    flat = np.full((420, 460), 128, np.uint8)
    assert blind_decode(flat, sharp.corners_px, BlindDecodeSettings()) is None


def test_stage1_counts_the_soft_decodes_and_skips_quads_inside_tags_it_has() -> None:
    sample = next(
        s
        for s in (render_sample(i, 3, SMALL_BLURRED) for i in range(60))
        if s.meta["blur_px"] >= 10.0
        and not LineQuadProposer(HARD).detect(s.image)
        and LineQuadProposer(SOFT).detect(s.image)
    )
    no_apriltag = DetectorSettings(min_decision_margin=1e9)
    stage1 = Stage1Detector(Stage1Settings(apriltag=no_apriltag, aruco=ArucoSettings(enabled=False), lines=SOFT))
    assert [(d.tag_id, d.proposer) for d in stage1.detect(sample.image)] == [(sample.tags[0].tag_id, "lines_soft")]
    assert (stage1.counts.lines_added, stage1.counts.lines_soft) == (1, 1)
    off = Stage1Detector(Stage1Settings(apriltag=no_apriltag, aruco=ArucoSettings(enabled=False), lines=HARD))
    assert off.detect(sample.image) == [] and off.counts.lines_soft == 0  # nothing read blind when off
    off.close()
    # a tag another proposer already has is not read again
    lines = LineQuadProposer(SOFT)
    assert lines.detect(sample.image, known=[sample.tags[0].corners_px]) == []
    assert lines.soft_decoded == 0
    stage1.close()


@pytest.mark.parametrize("field", ["max_blur_cells", "min_correlation", "angle_step_deg"])
def test_out_of_range_soft_decode_settings_are_refused(field: str) -> None:
    from shared.vision.softdecode import BlindDecodeSettings

    bad = {"max_blur_cells": -1.0, "min_correlation": 1.5, "angle_step_deg": 0.0}[field]
    with pytest.raises(pydantic.ValidationError, match=field):
        BlindDecodeSettings(**{field: bad})
    with pytest.raises(pydantic.ValidationError, match="soft"):
        LineQuadSettings(soft={field: bad})


def test_tags_another_proposer_found_are_not_refined_again() -> None:
    """A tag stage 1 already has (`others`: the same id where the line quad lies) comes back with its
    corners as the line quads read them, not refined (Stage1Detector drops it as a duplicate: refining
    it was 1.9 ms of a demo frame); another id there, or the same id elsewhere, leaves it refined."""
    from shared.vision.detector import Detection
    from shared.vision.linequads import refine_corners

    image = _draw(None, 117)
    (refined,) = LineQuadProposer().detect(image)
    same = Detection(117, 50.0, 0, refined.corners_px + 0.7, "apriltag")
    (raw,) = LineQuadProposer().detect(image, others=[same])
    assert not np.allclose(raw.corners_px, refined.corners_px, atol=1e-6)  # (refining moves them)
    np.testing.assert_allclose(refine_corners(image, raw.corners_px), refined.corners_px)
    assert raw.tag_id == 117 and raw.proposer == "lines"
    elsewhere = replace(same, corners_px=same.corners_px + 400.0)
    for other in (replace(same, tag_id=118), elsewhere):
        (kept,) = LineQuadProposer().detect(image, others=[other])
        np.testing.assert_allclose(kept.corners_px, refined.corners_px)
