"""Tensor containers shared by the torch EKF, the data loader and the trainer."""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass
class WindowBatch:
    """B windows of T consecutive epochs with N padded satellite slots (float64 geometry).

    Built by ``learning.data`` from ``lfgnss.sequence.Sequence`` objects; the field meanings are the
    Sequence's. ``features`` are normalised; ``truth_ecef_m`` is NaN where unlabelled.
    """

    time_gps_s: torch.Tensor        # (B, T) float64
    pr_m: torch.Tensor              # (B, T, N) float64
    sat_pos_ecef_m: torch.Tensor    # (B, T, N, 3) float64
    system_index: torch.Tensor      # (B, T, N) int64, -1 padded
    mask: torch.Tensor              # (B, T, N) bool
    features: torch.Tensor          # (B, T, N, d) float32, normalised
    coarse_ecef_m: torch.Tensor     # (B, T, 3) float64, NaN where no coarse fix
    coarse_clock_m: torch.Tensor    # (B, T, C) float64
    truth_ecef_m: torch.Tensor      # (B, T, 3) float64
    prr_m_s: torch.Tensor | None = None           # (B, T, N) float64, Doppler pseudorange rate
    prr_mask: torch.Tensor | None = None          # (B, T, N) bool
    sat_vel_ecef_m_s: torch.Tensor | None = None  # (B, T, N, 3) float64
    cn0_dbhz: torch.Tensor | None = None          # (B, T, N) float64, raw C/N0 (the Doppler variance's)
    glonass: torch.Tensor | None = None           # (B, T, N) bool, GLONASS slots (EkfConfig.glonass_sigma_factor)

    def __post_init__(self) -> None:
        if self.prr_mask is None:               # no Doppler: zeros, nothing usable
            self.prr_m_s = torch.zeros_like(self.pr_m)
            self.prr_mask = torch.zeros_like(self.mask)
            self.sat_vel_ecef_m_s = torch.zeros_like(self.sat_pos_ecef_m)
        if self.cn0_dbhz is None:               # unknown: NaN, refused by a C/N0-dependent Doppler variance
            self.cn0_dbhz = torch.full_like(self.pr_m, float("nan"))
        # glonass None: unknown, refused by a GLONASS sigma factor other than 1 (learning.torch_ekf.batch_ekf)

    def to(self, device: torch.device | str) -> "WindowBatch":
        """The same batch on another device."""
        return WindowBatch(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name).to(device)
                              for f in fields(self)})
