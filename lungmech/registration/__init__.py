"""Shape registration of a reference mesh onto segmented 3-D images, and shape modes from a
library of such mappings.

``image`` (segmentations with their geometry: NIfTI, MetaImage/NRRD, NumPy) → ``field`` (the
image function I, < 0 inside) → ``sobolev.register`` (Sobolev-gradient descent of ∫_ω I dx from a
moments-based similarity fit) → ``metrics`` (Dice, surface distances) → ``library`` (similarity
removal, mass-weighted POD, leave-one-out error, new geometries from shape coefficients).
``phantom`` makes synthetic lung images with exact ground truth, and cohorts of them.
"""
