"""LF-GNSS learning: noise network, differentiable EKF training, model files.

Modules (imported on demand so that numpy-only users of ``learning.export`` need no torch):
``network`` (LfgnssNet), ``loss`` (HEM / RMSE), ``normalise`` (Normaliser), ``data`` (windows ->
WindowBatch), ``torch_ekf`` (batched differentiable EKF), ``train`` (CLI and loop), ``crossval``
(blocked K-fold check of a recipe on train + validation epochs), ``export`` (model file and numpy inference).
"""
