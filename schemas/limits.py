"""What a plausible message holds: bounds every received message is checked against.

A well-formed message can still carry values no sensor or estimator produces (a marker 1e300 m
away, a variance of 1e-40, a stamp from before 1970 or next year, a million poses). Such values
pass protobuf and finiteness checks and then break whoever trusts them: a solver meets an
indeterminate system, an MCAP writer a negative time. ``WireLimits`` names the bounds; the codec
checks them at the one validation point of each message type (``schemas.codec``), and
``check_on_key`` checks what needs the key or the receiver's clock. Every refusal names its
reason, one of ``REASONS``, which services count per key.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

#: Why a message was refused, as counted per key (``cellsight status`` shows them).
REASONS = (
    "malformed",  # not the key's message type, or fields our schema does not define
    "not_finite",  # NaN or infinity where a number must be finite
    "not_rigid",  # a pose that is not a rotation and a translation
    "covariance",  # a covariance that is not symmetric positive definite within the bounds
    "out_of_bounds",  # a finite value outside what the cell can hold (positions, sizes, ids)
    "stamp",  # a stamp outside the window of the receiver's clock
    "id_mismatch",  # a camera id that is not the one of the key the message came on
    "too_many",  # more items in one message than the limit
    "invalid_id",  # an id that cannot be a key chunk
)


class WireLimits(BaseModel):
    """Bounds on received values (``[wire]`` in the cell config). Defaults fit a work cell of a few
    metres with room to spare; the covariance bounds keep every factor the estimator builds well
    conditioned (information at most 1e12 against the weakest prior's 1e-4)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    max_position_m: float = Field(
        default=100.0,
        gt=0,
        description="largest |x|, |y| or |z| of any position received (m): the cell's size with margin",
    )
    min_sigma: float = Field(
        default=1e-6,
        gt=0,
        description="smallest standard deviation a covariance may claim (m for positions, rad for rotations)",
    )
    max_sigma_rad: float = Field(default=10.0, gt=0, description="largest rotation standard deviation (rad)")
    max_marker_side_m: float = Field(default=10.0, gt=0, description="largest printed marker side (m)")
    max_marker_id: int = Field(
        default=65535, ge=0, description="largest marker id (OpenCV's dictionaries stop at 2,320)"
    )
    max_items: int = Field(
        default=65536, ge=1, description="most items in one message: markers, poses, transforms, objects, cameras"
    )
    max_image_side_px: int = Field(default=16384, ge=1, description="largest image width or height (pixels)")
    max_stamp_ahead_s: float = Field(
        default=86400.0,
        gt=0,
        description="how far a stamp may be ahead of the receiver's clock (s): a sensor whose clock "
        "stepped is taken back onto its timeline (hours); a stamp a day ahead is not a clock",
    )
    max_stamp_age_s: float | None = Field(
        default=None,
        gt=0,
        description="how far a stamp may be behind the receiver's clock (s); unset: any positive stamp, "
        "since `cellsight replay` publishes a log's original stamps, however old",
    )

    @property
    def max_sigma_m(self) -> float:
        """Largest position standard deviation (m): the cell's size."""
        return self.max_position_m


#: The defaults, for readers without a cell config (logs, tools).
DEFAULT_LIMITS = WireLimits()
