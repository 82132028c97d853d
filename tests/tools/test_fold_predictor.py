"""tools/fold_predictor.py: IMAGE_BLEND's folds foretold from the curves and the weights'
slope, against the exact counter, and the matrix determinant lemma it rests on."""

import numpy as np

import fixtures.rigs as rigs
from fixtures.masks import disk_masks
from fixtures.tools import load_tool
from multiscale_camera.core.quality.report import fold_map

fp = load_tool("fold_predictor")


def test_predicted_folds_lie_on_counted_ones_on_the_turned_rig():
    cams, masks = rigs.turned_rig(192, 108)
    fld = fp.blend_field(cams, masks)
    counted, _stride = fold_map(fld, 1)
    c = fp.compare(counted, fp.predict(fld)["folds"])
    assert c["counted"] > 1000  # the rig folds (the 2-3 and 1-2 transitions)
    assert c["false_near"] == 0  # no prediction more than one quad from a counted fold
    assert c["both"] >= 0.8 * c["counted"]
    assert c["missed_near"] <= 0.05 * c["counted"]


def test_no_fold_predicted_where_none_is_counted():
    cams, masks = rigs.zoom1000_rig(96, 54)
    fld = fp.blend_field(cams, masks)
    counted, _stride = fold_map(fld, 1)
    pred = fp.predict(fld)
    assert not counted.any() and not pred["folds"].any()
    assert pred["lemma"].min() > 0.5


def test_ratio_is_one_plus_slope_dot_separation_for_two_cameras():
    """det(M + u g^T) / det(M) = 1 + g . M^-1 u, with M^-1 u solved here in a basis of
    each section's plane: the predictor's section determinants, recomputed by hand."""
    # the turned rig's cameras 2 and 3 alone, the second's disk within the first's
    cams = rigs.turned_rig(48, 36)[0][1:]
    fld = fp.blend_field(cams, disk_masks(48, 36, 0.12 * 48, 0.2 * 48))
    w = fld.weights.astype(np.float64)[0]  # camera 1's weight; camera 2's is 1 - w
    inside = (w > 0) & (w < 1)  # the transition's pixels
    qy, qx = np.nonzero(inside[:-1, :-1] & inside[1:, 1:] & inside[:-1, 1:] & inside[1:, :-1])
    qy, qx = qy[::7], qx[::7]  # a sample of its quads all round
    det, det_m, active = fp.quad_sections(fld, qy, qx)
    seen = []
    for q, (y, x) in enumerate(zip(qy, qx)):
        wc = 0.25 * (w[y, x] + w[y, x + 1] + w[y + 1, x] + w[y + 1, x + 1])
        g = np.array(
            [
                0.5 * ((w[y, x + 1] - w[y, x]) + (w[y + 1, x + 1] - w[y + 1, x])),
                0.5 * ((w[y + 1, x] - w[y, x]) + (w[y + 1, x + 1] - w[y, x + 1])),
            ]
        )
        cx, cy = np.array([x + 1.0]), np.array([y + 1.0])

        def curves(px, py):
            return fp._curves(cams, px, py, fld.rig.beta)[:, 0]  # (2, K, 3)

        r = curves(cx, cy)
        jx = curves(cx + 0.5, cy) - curves(cx - 0.5, cy)
        jy = curves(cx, cy + 0.5) - curves(cx, cy - 0.5)
        p = wc * r[0] + (1 - wc) * r[1]
        for k in range(1, p.shape[0]):  # section 0: every curve at p_1, u = 0
            t = p[min(k + 1, len(p) - 1)] - p[k - 1]
            t /= np.linalg.norm(t)
            e1 = np.cross(t, [0.0, 0.0, 1.0])
            e1 /= np.linalg.norm(e1)
            basis = np.stack([e1, np.cross(t, e1)])  # (2, 3), right-handed with t
            mx = wc * jx[0][k] + (1 - wc) * jx[1][k]
            my = wc * jy[0][k] + (1 - wc) * jy[1][k]
            m = basis @ np.stack([mx, my], axis=1)
            s = np.linalg.solve(m, basis @ (r[0][k] - r[1][k]))
            expected = 1.0 + g @ s
            # float32 weights sum to one within about 1e-7 (camera 2's is taken as 1 - w)
            assert abs(det[q, k] / det_m[q, k] - expected) < 1e-6 * max(1.0, abs(expected))
            seen.append(expected)
    # the weights' slope counts there, turning quads both ways
    assert len(qy) > 10 and min(seen) < 0.9 and max(seen) > 1.1
