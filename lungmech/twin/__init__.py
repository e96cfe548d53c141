"""The digital twin: a patient's lung parameters from images, with their uncertainty.

``surface`` (what a segmentation tells of a state: the signed distance to its surface and its
volume; a mesh's surface nodes and their areas) → ``fit`` (the least-squares problem of one or
more image pairs on any model that answers ``solve(μ, sensitivities=True)``, and its bounded
estimate) → ``uncertainty`` (the Laplace covariance, the model's error as a bias, intervals,
identifiability, a check by resampling); beside them ``ventilation`` (the volume change from
end-expiration to end-inspiration, fitted and registered) and ``synthetic`` (patients made by a
model at known parameters, and the noise of twin experiments).
"""
