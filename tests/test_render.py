"""``jrt render`` end to end: the PNG's camel silhouette against Embree's hit mask."""

from __future__ import annotations

import numpy as np
from skimage import io

from jrt.camera import camera_rays, frame_mesh
from jrt.cli import main
from jrt.render import silhouette


def test_render_silhouette_matches_embree(camel, embree_camel, tmp_path, capsys):
    out = tmp_path / "camel.png"
    width, height = 320, 240
    assert main(["render", "-o", str(out), "--width", str(width), "--height", str(height)]) == 0
    printed = capsys.readouterr().out
    assert "320x240" in printed and "Mrays/s" in printed and "shadow rays" in printed
    image = io.imread(out)
    assert image.shape == (height, width, 3) and image.dtype == np.uint8

    camera = frame_mesh(camel.vertices, width=width, height=height)  # the CLI's default view
    origins, directions = camera_rays(camera)
    ref = embree_camel.closest_hit(np.asarray(origins), np.asarray(directions))
    ref_mask = (ref["triangle"] >= 0).reshape(height, width)
    mask = silhouette(image)
    iou = (mask & ref_mask).sum() / (mask | ref_mask).sum()
    print(f"\nsilhouette: {mask.sum()} px, Embree {ref_mask.sum()} px, IoU {iou:.5f}")
    assert ref_mask.sum() > 0.05 * mask.size
    assert iou >= 0.999
    # Shading: lit and shadowed pixels differ (the lamp and the shadow rays did something).
    lum = image[mask].astype(float).mean(axis=1)
    assert lum.max() - lum.min() > 80
