"""Image pairs by retrieval: pairs that grow linearly with the photos, for captures whose names
give no order.

Each image gets a global descriptor built from its own SIFT features: VLAD over a small
vocabulary that k-means learns from the capture itself (no download, no training data), with
RootSIFT features, per-word normalisation and a signed square root. Each image is then paired
with the `k` images whose descriptors are most alike, so `n` images cost at most `n * k` pairs
instead of `n (n - 1) / 2`. Pure NumPy; the descriptors come from the SfM database
(`colmap.read_descriptors`).
"""

from __future__ import annotations

import numpy as np

WORDS = 64  # the vocabulary: enough words to tell places apart, few enough to learn from one capture
SAMPLE_PER_IMAGE = 256  # descriptors per image the vocabulary learns from
KMEANS_ITERS = 12


def root_sift(desc: np.ndarray) -> np.ndarray:  # [n, 128] uint8 -> [n, 128] float32, unit L2 norm
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(d)


def _nearest(x: np.ndarray, centers: np.ndarray) -> np.ndarray:  # [n, D], [K, D] -> [n] int
    d2 = (centers * centers).sum(1)[None, :] - 2.0 * (x @ centers.T)  # |x|^2 dropped: the same for every centre
    return d2.argmin(axis=1)


def _word_sums(a: np.ndarray, x: np.ndarray, k: int) -> np.ndarray:  # [n] int, [n, D] -> [k, D]
    """The rows of x summed per word a, as one product with the words' one-hot matrix (np.add.at,
    row by row, took most of the retrieval's time: 20 s for 250 video frames)."""
    onehot = np.zeros((k, len(a)), x.dtype)
    onehot[a, np.arange(len(a))] = 1
    return onehot @ x


def vocabulary(descs: list[np.ndarray], words: int = WORDS, seed: int = 0) -> np.ndarray:
    """k-means centres [K, 128] learnt from a seeded sample of every image's RootSIFT features
    (`descs`: each image's SIFT descriptors, uint8)."""
    rng = np.random.default_rng(seed)
    sample = [root_sift(d[rng.choice(len(d), min(len(d), SAMPLE_PER_IMAGE), replace=False)]) for d in descs if len(d)]
    x = np.concatenate(sample) if sample else np.zeros((0, 128), np.float32)
    k = min(words, len(x))
    if k == 0:
        return np.zeros((0, 128), np.float32)
    centers = x[rng.choice(len(x), k, replace=False)].copy()
    for _ in range(KMEANS_ITERS):
        a = _nearest(x, centers)
        sums = _word_sums(a, x, k)
        counts = np.bincount(a, minlength=k)[:, None]
        empty = counts[:, 0] == 0
        centers = np.where(empty[:, None], centers, sums / np.maximum(counts, 1))
    return centers


def vlad(desc: np.ndarray, centers: np.ndarray) -> np.ndarray:  # [n, 128] RootSIFT, [K, 128] -> [K * 128]
    """One image's VLAD: residuals summed per word, each word normalised, a signed square root,
    then unit length (an image without features gets zeros: alike to nothing)."""
    k, dim = centers.shape
    v = np.zeros((k, dim), np.float32)
    if len(desc) and k:
        a = _nearest(desc, centers)
        v = _word_sums(a, desc - centers[a], k)
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    v = np.sign(v) * np.sqrt(np.abs(v))
    flat = v.reshape(-1)
    return flat / max(float(np.linalg.norm(flat)), 1e-12)


def similarity(descs: list[np.ndarray], seed: int = 0) -> np.ndarray:  # -> [n, n]
    """Cosine similarity of the images' VLAD descriptors (module docstring), -inf on the diagonal.
    `descs[i]` holds image i's SIFT descriptors, [n_i, 128] uint8."""
    centers = vocabulary(descs, seed=seed)
    g = np.stack([vlad(root_sift(d), centers) for d in descs]) if descs else np.zeros((0, 0), np.float32)  # [n, K * 128]; one image's floats at a time
    sim = g @ g.T  # [n, n] cosine
    np.fill_diagonal(sim, -np.inf)
    return sim


def nearest_pairs(names: list[str], sim: np.ndarray, k: int, of: set[str] | None = None) -> list[tuple[str, str]]:
    """Each image (each of `of`, None: all) with the `k` images most alike by `sim` [n, n]; pairs in
    `names`' order, each once."""
    n = len(names)
    k = min(k, n - 1)
    out = set()
    for i in range(n):
        if k <= 0 or (of is not None and names[i] not in of):
            continue
        for j in np.argsort(-sim[i], kind="stable")[:k]:
            out.add((min(i, int(j)), max(i, int(j))))
    return [(names[i], names[j]) for i, j in sorted(out)]


def retrieval_pairs(names: list[str], descs: list[np.ndarray], k: int, seed: int = 0) -> list[tuple[str, str]]:
    """Each image with the `k` images most alike (VLAD, module docstring); pairs in `names`' order,
    each once. `descs[i]` holds image i's SIFT descriptors, [n_i, 128] uint8."""
    if len(names) < 2:
        return []
    return nearest_pairs(names, similarity(descs, seed), k)
