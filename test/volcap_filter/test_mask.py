"""The clean-plate mask's clean-up."""
import numpy as np

from volcap_filter.mask import clean_mask


def test_clean_mask_on_the_subjects_box_equals_the_whole_frame():
    """clean_mask works on the box around the opened foreground; the result is the full-frame
    computation's, pixel for pixel (holes, small blobs, unseeded blobs, blobs on the border)."""
    import cv2

    def whole_frame(fg, min_area_frac, seeds=None):
        m = cv2.morphologyEx(fg.view(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        keep = stats[:, cv2.CC_STAT_AREA] >= min_area_frac * fg.size
        keep[0] = False
        if seeds is not None:
            touched = np.zeros(n, bool)
            touched[labels[seeds]] = True
            keep &= touched
        padded = cv2.copyMakeBorder(keep[labels].view(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
        cv2.floodFill(padded, None, (0, 0), 2)
        return padded[1:-1, 1:-1] != 2
    rng = np.random.default_rng(0)
    for k in range(120):
        fg = rng.random((72, 128)) < rng.uniform(0.01, 0.6)
        if k % 3 == 0:     # a subject with a hole, and speckle
            fg[:] = False
            fg[10:50, 30:60] = True
            fg[20:30, 40:45] = False
            fg[rng.random(fg.shape) < 0.05] = True
        seeds = rng.random(fg.shape) < 0.1 if k % 2 else None
        np.testing.assert_array_equal(clean_mask(fg, 0.002, seeds), whole_frame(fg, 0.002, seeds))
    assert not clean_mask(np.zeros((8, 8), bool), 0.0).any()
