"""The HOG detector's library parts against the hand-written code they replaced (kept here as the
reference): non-maximum suppression (``cv2.dnn.NMSBoxes``) keeps exactly the same boxes in the same
order; the SVM (scikit-learn's ``LinearSVC``, liblinear) solves the same squared-hinge problem as the
L-BFGS primal solver did: weights within 1e-3 in cosine, the objective within 0.1 %, the same sign on
99.5 % of the samples."""
import numpy as np
import pytest
from scipy.optimize import minimize

from stack.topomap.hog_detector import iou, nms, train_linear_svm


def nms_reference(boxes, scores, threshold=0.4):
    order = np.argsort(-scores)
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        if len(order) == 1:
            break
        o = iou(boxes[i:i + 1], boxes[order[1:]])[0]
        order = order[1:][o <= threshold]
    return np.array(keep, dtype=int)


def svm_reference(X, y, C=0.01, pos_weight=1.0, max_iter=400):
    cw = np.where(y > 0, pos_weight, 1.0) * C
    d = X.shape[1]

    def f(p):
        w, b = p[:d], p[d]
        m = 1 - y * (X @ w + b)
        act = m > 0
        g = -2 * cw[act] * m[act] * y[act]
        return 0.5 * w @ w + np.sum(cw[act] * m[act] ** 2), np.r_[w + X[act].T @ g, g.sum()]

    res = minimize(f, np.zeros(d + 1), jac=True, method="L-BFGS-B", options={"maxiter": max_iter})
    return res.x[:d], float(res.x[d])


def objective(w, b, X, y, C, pos_weight):
    m = np.maximum(0.0, 1 - y * (X @ w + b))
    return 0.5 * w @ w + C * np.sum(np.where(y > 0, pos_weight, 1.0) * m ** 2)


@pytest.mark.parametrize("seed", range(5))
def test_nms_keeps_the_same_boxes(seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 300, (150, 2))
    wh = rng.uniform(10, 80, (150, 2))
    boxes = np.column_stack([xy, xy + wh])
    scores = rng.normal(0, 1, 150)  # SVM margins: negative ones too
    for thr in (0.3, 0.5):
        np.testing.assert_array_equal(nms(boxes, scores, thr), nms_reference(boxes, scores, thr))
    assert len(nms(np.zeros((0, 4)), np.zeros(0))) == 0


@pytest.mark.parametrize("C,pos_weight", [(0.01, 5.0), (1.0, 1.0)])
def test_svm_solves_the_same_problem(C, pos_weight):
    rng = np.random.default_rng(0)
    d, n_pos, n_neg = 120, 150, 1200  # HOG-like: non-negative, truncated features
    mean_pos = rng.uniform(0, 0.2, d)
    Xp = np.clip(mean_pos + rng.normal(0, 0.08, (n_pos, d)), 0, 0.2)
    Xn = np.clip(rng.uniform(0, 0.2, d) + rng.normal(0, 0.08, (n_neg, d)), 0, 0.2)
    X = np.vstack([Xp, Xn])
    y = np.r_[np.ones(n_pos), -np.ones(n_neg)]
    w_r, b_r = svm_reference(X, y, C, pos_weight)
    w_n, b_n = train_linear_svm(X, y, C, pos_weight)
    assert w_n @ w_r / np.linalg.norm(w_n) / np.linalg.norm(w_r) > 0.999
    f_r, f_n = objective(w_r, b_r, X, y, C, pos_weight), objective(w_n, b_n, X, y, C, pos_weight)
    assert abs(f_n - f_r) <= 1e-3 * f_r
    assert np.mean(np.sign(X @ w_n + b_n) == np.sign(X @ w_r + b_r)) >= 0.995
