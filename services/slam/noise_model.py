"""The estimator's noise model as variances (docs/estimator.md): the standard model's
σv², σω², σr², σφ² and the opt-in motion and range terms, with the per-step and
per-observation variances they make. Pure arithmetic on settings; no state.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.services.slam.settings import EstimatorSettings


@dataclass(frozen=True)
class NoiseModel:
    """Variances of the documented model; the opt-in terms are 0 unless configured."""

    var_v: float  #: σv², (m/s)²
    var_w: float  #: σω², (rad/s)²
    var_r: float  #: σr², m²
    var_b: float  #: σφ², rad²
    q_range: float = 0.0  #: k² of the range term (k·r)²
    q_off_axis: float = 0.0  #: k² of the off-axis range term (k·r·φ²)²
    q_dist: float = 0.0  #: extra speed variance per m driven
    q_turn: float = 0.0  #: extra turn variance per rad turned
    q_head_dist: float = 0.0  #: extra turn variance per m driven

    @classmethod
    def of(cls, settings: EstimatorSettings) -> NoiseModel:
        """The model ``settings`` configure."""
        return cls(var_v=settings.sigma_v ** 2, var_w=settings.sigma_w ** 2,
                   var_r=settings.sigma_range ** 2, var_b=settings.sigma_bearing ** 2,
                   q_range=settings.sigma_range_per_m ** 2,
                   q_off_axis=settings.sigma_range_off_axis ** 2,
                   q_dist=settings.sigma_distance ** 2, q_turn=settings.sigma_turn ** 2,
                   q_head_dist=settings.sigma_heading_per_distance ** 2)

    def motion_extra(self, v: float, w: float, dt: float) -> tuple[float, float]:
        """The opt-in motion terms' extra (speed, turn) variances for one step (0, 0 when
        none is configured: docs/estimator.md exactly)."""
        if not (self.q_dist or self.q_turn or self.q_head_dist):
            return 0.0, 0.0
        dist, turn = abs(v * dt), abs(w * dt)
        return self.q_dist * dist, self.q_turn * turn + self.q_head_dist * dist

    def range_variance(self, z_range: float, z_bearing: float) -> float:
        """σr², plus the opt-in terms (k·r)² and (k·r·φ²)² when configured."""
        var = self.var_r
        if self.q_range:
            var += self.q_range * z_range * z_range
        if self.q_off_axis:
            off = z_range * z_bearing * z_bearing
            var += self.q_off_axis * off * off
        return var
