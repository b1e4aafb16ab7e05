"""Tracker parameters: one frozen dataclass, named profiles, every module switchable.

Values follow docs ALGORITHM.md: `authors` are the values in force in the authors' MATLAB code (section 1),
`paper` replaces them with the paper's where the paper states one (section A), `kcc` is the ablation baseline
with all three attentions off.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

PROFILES = ("paper", "authors", "kcc")
DEFAULT_PROFILE = "paper"  # the higher mean success AUC on the UAV sequences; see README "Accuracy"


# Ceilings, most far above any sensible setting (the defaults are 4, 200^2, 33, 1.03, 512, 4 (`paper`: 2), 32, and for
# the sigmas 0.5, 1/40, 1/16): the square of a sigma over 1e154 overflows, and init failed with a math range error;
# a label factor over 1 makes the label wider than the target. cn_poly_a: float32 keeps 7 digits, which the
# products x.z / N (at most 1) lose beside a larger offset (1e4 cut the PME to a third; with 1e6 Color Names
# answered nothing).
LIMITS = {"cell_size": 16, "fixed_area": 1000.0**2, "num_scales": 129, "scale_step": 2.0,
          "scale_model_max_area": 64.0**2, "context_interval": 1000, "hist_bins": 256,
          "hog_kernel_sigma": 1e6, "hog_output_sigma_factor": 1.0, "cn_output_sigma_factor": 1.0,
          "lambda1": 1e6, "scale_lambda": 1e6, "cn_poly_a": 1e3,
          # each of these far past its ceiling (1e20, 1e38, 1e39, 1e100) took PME to 0 on every frame: a frozen box
          "context_penalty_total": 1e3, "context_lambda2": 1e6, "dim_floor": 10.0, "dim_threshold": 10.0,
          "motion_gain": 100.0, "scale_sigma_factor": 1e3,
          # a challenge factor is a PME ratio, the context's over the target's: a floor above every ratio splits the
          # penalties evenly whatever it is, and past 1e154 its square overflowed (inf / inf, the model NaN for good)
          "context_challenge_floor": 1e3}
# Floors where > 0 is not enough. The models are float32: 1/lambda overflows under ~3e-39 and lambda over 3.4e38,
# turning the filters NaN; 1e-12 .. 1e6 leaves wide margins around the paper's 5e-5 and the code's 1e-4 (from ~1
# up the filters are all regularisation and barely follow the target, but nothing breaks). A label's sigma is
# about 25 cells times its factor at the default area: at 1e-3 the label is one cell, at 1e-300 its square
# underflowed (a NaN label). A challenge floor of 0 (or 1e-200, whose square underflows) gave 0/0 penalties when
# all four context responses were flat. One histogram bin gives every pixel the same likelihood: the colour window
# (Staple: the colour response) silently flat. num_scales: see TrackerConfig.num_scales.
# A negative lambda2 or Color Names offset turned the model NaN for good; a negative motion gain means nothing
# (-100 cut the PME to 0.6); a dimensional floor of 0 (past a high threshold) can weigh every channel 0.
FLOORS = {"lambda1": 1e-12, "scale_lambda": 1e-12, "hog_output_sigma_factor": 1e-3, "cn_output_sigma_factor": 1e-3,
          "context_challenge_floor": 1e-3, "hist_bins": 2, "num_scales": 5, "context_lambda2": 0.0,
          "context_penalty_total": 0.0, "cn_poly_a": 0.0, "motion_gain": 0.0, "dim_floor": 1e-3,
          "dim_threshold": -10.0, "scale_sigma_factor": 1e-3}
# Combinations the tracker can run (defaults: 2,500 cells, scales up to 1.6 times the target, 32 bins, sigma 0.5).
# Under 48 cells a long thin target's cropped response can be a single cell (at 40, targets of 1:20 and 1:50 had
# one), and a one-cell response never moves the box; 48 gives at least 3 for every aspect ratio up to 1:50.
MIN_CELLS, MAX_CELLS = 48, 250.0**2         # 1000^2 pixels in cells of 4
MAX_SCALE_RANGE = 4.0
MAX_HIST_BINS = 64
MIN_KERNEL_SIGMA = 0.01                     # 1e-6 turned the HOG model NaN
# Color Names' cells sum to 1, so x.z / N <= 1 and the polynomial kernel is at most (1 + a)^b; float32 squares its
# transform, up to MAX_CELLS times that: 1e12 keeps it finite with a margin (a = 100, b = 50 turned the model NaN).
MAX_CN_KERNEL = 1e12
# ... and at the other end, Color Names' correlations per channel are small (x.z / N of 1e-4 to 0.03 on person12_1):
# the kernel must still change by lambda1 across a weak one (0.01), or the filter is all regularisation
# and Color Names answers nothing, silently. Its response's peak on person12_1's second frame: 1.84 at the defaults
# (a = 1, b = 2), 0.11 at (0, 2), 0.005 at (0.5, 20), 1e-10 at (0, 5) and (0.1, 10), 0 at (0.001, 20).
WEAK_CN_CORRELATION = 0.01
MIN_CN_CHANGE = 1e-4                        # the `authors` lambda1 (`paper`'s, 5e-5, sets a lower floor)
# Off its DC term the HOG kernel's spectrum falls as 1 / hog_kernel_sigma^2 once the sigma is wide, and the filter's
# answer as 1 / (lambda1 sigma^4), until float32 loses it beside the response's constant part. Only that product
# counts (kcc with HOG alone: about the same boxes for any pair): at 1e6 a generated target was still followed (IoU
# 0.64-0.74; 0.97 at 6e-6, the `authors` and `kcc` product, `paper`'s being 3e-6), at 1e7 lost, its responses flat
# on some frames (PME 0, the box frozen); on the first 25 frames of five UAV sequences, mean IoU 0.1 at 1e7 and boxes
# frozen from 2e7.
MAX_HOG_DAMPING = 1e6


def _past_float_range(value) -> bool:
    """Whether `value` is a number no float holds: an int or a Fraction past 1.8e308 (lambda1=10**400 failed in
    init; math.isfinite and float() raise OverflowError on it)."""
    if isinstance(value, numbers.Real) and not isinstance(value, float):
        try:
            float(value)
        except OverflowError:
            return True
    return False


def check_fields(config, positive: tuple[str, ...], rates: tuple[str, ...]) -> None:
    """Validate a frozen config dataclass: each field of its declared type and finite, the `positive` ones > 0,
    the `rates` in [0, 1], the scale filter's step > 1 and count odd, and every field named in FLOORS or LIMITS
    within them."""
    # numpy here, not at the top: every `tacf` command imports this module (PROFILES), and numpy took 60-110 ms of
    # `tacf --help`
    import numpy as np
    name = type(config).__name__
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        if _past_float_range(v):    # not printed: an int of over 4,300 digits raises in str(), naming no field
            wanted = {"float": "finite", "int": "an int within its bounds"}.get(f.type, f.type)
            raise ValueError(f"{name}.{f.name} must be {wanted}, got a number past the float range")
        # numpy scalars (a sweep read from an array) count as their Python kinds, and are stored as them so that
        # dataclasses.asdict() stays JSON; bool is an int in Python: num_scales=True must not pass as 1, nor 1.0 as True
        is_bool = isinstance(v, (bool, np.bool_))
        expected = {"bool": is_bool, "int": isinstance(v, numbers.Integral) and not is_bool,
                    "float": isinstance(v, numbers.Real) and not is_bool, "str": isinstance(v, str)}[f.type]
        if not expected:
            raise ValueError(f"{name}.{f.name} must be {f.type}, got {v!r}")
        if f.type == "float" and not math.isfinite(v):
            raise ValueError(f"{name}.{f.name} must be finite, got {v}")
        if f.type != "str":
            object.__setattr__(config, f.name, {"bool": bool, "int": int, "float": float}[f.type](v))
    for field in positive:
        if getattr(config, field) <= 0:
            raise ValueError(f"{name}.{field} must be > 0, got {getattr(config, field)}")
    for field in rates:
        if not 0.0 <= getattr(config, field) <= 1.0:
            raise ValueError(f"{name}.{field} must be in [0, 1], got {getattr(config, field)}")
    if config.scale_step <= 1.0:
        raise ValueError(f"{name}.scale_step must be > 1, got {config.scale_step}")
    if config.num_scales % 2 == 0:
        raise ValueError(f"{name}.num_scales must be odd, got {config.num_scales}")
    # Bounds: overrides arrive from the network, a huge area or scale count is a memory bomb, and the float32
    # models turn NaN at the extremes of some fields.
    for field in dict.fromkeys([*FLOORS, *LIMITS]):
        if not hasattr(config, field):
            continue
        low, high = FLOORS.get(field, -math.inf), LIMITS.get(field, math.inf)
        if not low <= getattr(config, field) <= high:
            allowed = (f"in [{low:g}, {high:g}]" if field in FLOORS and field in LIMITS
                       else f">= {low:g}" if field in FLOORS else f"<= {high:g}")
            raise ValueError(f"{name}.{field} must be {allowed}, got {getattr(config, field)}")


def shared_combination_problems(config) -> list[str]:
    """What the filter grid (fixed_area / cell_size**2 cells), the colour histogram (hist_bins cubed) and the scale
    filter's range of a config must be for its tracker to run: TrackerConfig's, and tacf.staple's StapleConfig's,
    whose fields alone let through a one-cell grid or 3 bins (init failed), 256 bins (16.7 M, a gigabyte) and scale
    patches up to 2**64 times the target (init failed)."""
    problems = []
    if config.hist_bins > MAX_HIST_BINS or 256 % config.hist_bins:
        problems.append(f"hist_bins must be a power of two up to {MAX_HIST_BINS} (its cube is the colour "
                        f"histogram's size), got {config.hist_bins}")
    cells = config.fixed_area / config.cell_size**2
    if not MIN_CELLS <= cells <= MAX_CELLS:
        problems.append(f"fixed_area / cell_size**2 (the filter's cells) must be in [{MIN_CELLS}, {MAX_CELLS}], "
                        f"got {cells:g}")
    widest = config.scale_step ** ((config.num_scales - 1) / 2)
    if widest > MAX_SCALE_RANGE:
        problems.append(f"scale_step ** ((num_scales - 1) / 2), the largest scale patch over the target, must "
                        f"be <= {MAX_SCALE_RANGE}, got {widest:g}")
    return problems


@dataclass(frozen=True)
class TrackerConfig:
    # The field defaults are the `authors` values; profile() builds the others. Not `profile`: that is the constructor.
    profile_name: str = "authors"

    # Module switches (the paper's ablation: KCC, +SA, +DA, +CA, all three).
    context_attention: bool = True
    dimensional_attention: bool = True
    spatiotemporal_attention: bool = True
    colour_window: bool = True
    scale_estimation: bool = True
    use_colour_names: bool = True

    # Geometry (Staple's areas with TACF's adaptive padding).
    cell_size: int = 4
    fixed_area: float = 200.0**2
    inner_padding: float = 0.2

    # Kernel correlators: Gaussian kernel on fHOG, polynomial (x.z/N + a)^b on Color Names.
    hog_kernel_sigma: float = 0.5
    cn_poly_a: float = 1.0
    cn_poly_b: float = 2.0
    hog_output_sigma_factor: float = 1.0 / 40
    cn_output_sigma_factor: float = 1.0 / 16
    lambda1: float = 1e-4
    learning_rate: float = 0.01

    # Contextual attention: context patches every `context_interval` frames, penalties from PME ratios.
    context_interval: int = 4
    context_lambda2: float = 1.0 / 256  # features are scaled by sqrt(lambda2) before the kernel
    context_penalty_total: float = 4.0  # the penalties sum to this (the paper: 1, the code: 4)
    context_challenge_floor: float = 0.3
    context_penalty_rate: float = 0.2  # EMA of the penalties across context frames
    # The challenge factors' responses use one multi-channel kernel over the 31 fHOG channels (KCF's), not the 31
    # per-channel ones detection uses: with the exact kernel 3 FFTs a context patch instead of 63 (with fast_kernel's
    # first-order one, one inverse FFT either way), and the same mean AUC on all 15 sequences of ../shared/data
    # (docs/decisions.md). False measures them exactly as detection would.
    context_pooled_kernel: bool = True

    # Dimensional attention: s_d = max(z_d - threshold, 0) + floor, EMA over frames.
    dim_threshold: float = 0.3
    dim_floor: float = 0.3
    dim_learning_rate: float = 0.022

    # Spatiotemporal attention: the paper's per-frame map (rate 1). The authors' code keeps an EMA at 0.02, which
    # only did no harm because its window was misaligned; aligned, it freezes frame 2's map into a prior on
    # frame 2's motion (person12_1: AUC 0.06 instead of 0.76). See docs/decisions.md.
    spatial_learning_rate: float = 1.0
    motion_gain: float = 2.0
    # The motion term shifts the map by gamma_t times the grid; past half the grid the code's roll wraps it round
    # behind the motion (48 of truck2's 450 motion terms). Stopped at the grid's edge instead: +0.008 one pass on
    # the 10 UAV sequences, +0.004 over the shifted starts, no sequence lower by more than 0.003 (docs/decisions.md).
    motion_term_wraps: bool = False

    # Colour histogram window (Staple-like, detection only).
    hist_bins: int = 32
    hist_learning_rate: float = 0.02
    likelihood_floor: float = 0.1  # in [0, 1]; 1 leaves the window all ones, as colour_window=False does more cheaply

    # DSST scale filter. At least 5 scales: the symmetric Hann window zeroes both ends, so 3 would sample the centre
    # scale alone and never change it. Few scales rarely change it either: on a target growing 3 % a frame for 19
    # frames (to 1.75 times), 5 to 13 scales stayed at 1.000, 17 and 33 followed (1.61, 1.65).
    num_scales: int = 33
    scale_step: float = 1.03
    scale_sigma_factor: float = 0.5
    scale_learning_rate: float = 0.025
    scale_lambda: float = 1e-4
    scale_model_max_area: float = 512.0
    # The scale filter measures and learns only while at least this fraction of the box lies in the frame: beyond
    # it the scale patches are repeated border pixels, and a target leaving through a corner grew the box up to
    # 5.9 times, ok all along (scale.ScaleFilter.sees_enough). 0 is the code's: always (docs/decisions.md).
    scale_min_visible: float = 0.5

    # Engineering: grow the filter grid to a fast FFT size (a few per cent more search area); shrink patches by
    # exact 2x2 halvings then bilinearly instead of one area resize (geometry.resize_auto; docs/decisions.md).
    fast_fft: bool = True
    fast_resize: bool = True
    fast_context: bool = True  # the four context patches cut from one sample covering them (Tracker._context_features)
    # The fHOG Gaussian kernel exp(-u) in its first-order form 1 - u, whose transform needs no FFT, while u provably
    # stays under correlator.FAST_KERNEL_EXPONENT (on every frame of the 15 sequences); docs/decisions.md.
    fast_kernel: bool = True

    # The peak refined between cells by a parabola on each axis of the cell-level fused response
    # (docs/decisions.md). False is the paper's and the code's peak: the upsampled response's, which bilinear
    # upsampling keeps on whole cells.
    subcell_peak: bool = True

    # Motion search (beyond the paper; docs/decisions.md): after a move of more than this fraction of the search
    # radius, the target is also searched for where that move continues, and the search whose HOG response
    # peaks higher is taken. On truck2 (UAV123@10fps) every profile otherwise falls behind the truck and loses it.
    motion_search: bool = True
    motion_search_threshold: float = 0.2

    # Output: the target counts as lost when the PME of the fused response falls under this floor. On the 10 UAV
    # sequences (`tacf eval`'s lost-flag table, 1,282 frames), the `paper` profile's flag at 20 catches 25 % of the
    # failures (IoU < 0.1) and flags 1 of 917 tracked frames (IoU > 0.5); before the motion search 23 % and none,
    # and 25 would have caught 40 % for 0.1 %. The attentions sharpen the response: without them (`kcc`) PME runs
    # at about half (median 40 on tracked frames against 84), so that profile's floor is 10, where it catches 20 %
    # and flags none of 819 (at 20, before the motion search: 7 % of the tracked frames).
    lost_pme: float = 20.0
    # ... and when less than this fraction of its box lies in the frame. A target that has left (through a corner,
    # generated) leaves the box at the edge, 0-4 % in view, following the background there with PMEs of 20-43; one
    # still leaving is followed to its last tenth in view. No box of the 15 sequences, over 9 starts each, comes
    # under 75 % in view.
    lost_min_visible: float = 0.1

    def __post_init__(self) -> None:
        check_fields(self, positive=("cell_size", "fixed_area", "hog_kernel_sigma", "cn_poly_b", "context_interval",
                                     "scale_sigma_factor", "scale_model_max_area"),
                     rates=("learning_rate", "context_penalty_rate", "dim_learning_rate", "spatial_learning_rate",
                            "hist_learning_rate", "likelihood_floor", "scale_learning_rate",
                            "scale_min_visible", "motion_search_threshold", "lost_min_visible"))
        self._check_combinations()

    def _check_combinations(self) -> None:
        """What each field's own bounds let through and the tracker cannot use: a model turned NaN, an area or
        a scale range that takes gigabytes and minutes (overrides arrive from the network)."""
        problems = []
        if self.hog_kernel_sigma < MIN_KERNEL_SIGMA:
            problems.append(f"hog_kernel_sigma must be >= {MIN_KERNEL_SIGMA}, got {self.hog_kernel_sigma}")
        hog_damping = self.lambda1 * self.hog_kernel_sigma**4
        if hog_damping > MAX_HOG_DAMPING:
            problems.append(f"lambda1 * hog_kernel_sigma**4, which damps the HOG filter's answer, must be <= "
                            f"{MAX_HOG_DAMPING:g}, got {hog_damping:g}")
        # cn_poly_b * log10(1 + cn_poly_a): (1 + a) ** b itself overflows a Python float (b = 1e5)
        cn_kernel_digits = self.cn_poly_b * math.log10(1 + max(self.cn_poly_a, 0.0))
        if cn_kernel_digits > math.log10(MAX_CN_KERNEL):
            problems.append(f"(1 + cn_poly_a) ** cn_poly_b, the Color Names kernel's largest value, must be <= "
                            f"{MAX_CN_KERNEL:g}, got 10**{cn_kernel_digits:.3g}")
        # log10 of b (a + w)^(b - 1) w, the kernel's slope times w: the power alone underflows (b = 1e5)
        cn_change_digits = (math.log10(self.cn_poly_b) + (self.cn_poly_b - 1) * math.log10(
            max(self.cn_poly_a, 0.0) + WEAK_CN_CORRELATION) + math.log10(WEAK_CN_CORRELATION))
        # (a lambda1 over 1e-4 weakens every filter alike, which is allowed: see FLOORS)
        cn_change_floor = min(self.lambda1, MIN_CN_CHANGE)
        if cn_change_digits < math.log10(cn_change_floor):
            problems.append(f"cn_poly_b * (cn_poly_a + {WEAK_CN_CORRELATION:g}) ** (cn_poly_b - 1) * "
                            f"{WEAK_CN_CORRELATION:g}, the Color Names kernel's change over a weak correlation, must "
                            f"be >= {cn_change_floor:g} (lambda1, at most {MIN_CN_CHANGE:g}), or Color Names answers "
                            f"nothing; got 10**{cn_change_digits:.3g}: raise cn_poly_a or lower cn_poly_b")
        problems += shared_combination_problems(self)
        if problems:
            raise ValueError("TrackerConfig: " + "; ".join(problems))

    @classmethod
    def profile(cls, name: str = DEFAULT_PROFILE, **overrides) -> "TrackerConfig":
        """A named parameter set, optionally with some fields replaced: profile("paper", lambda1=1e-4)."""
        if name == "authors":
            base = cls(profile_name="authors")
        elif name == "paper":
            base = cls(profile_name="paper", lambda1=5e-5, context_interval=2, context_lambda2=0.0625,
                       context_penalty_total=1.0, dim_floor=0.1)
        elif name == "kcc":
            base = cls(profile_name="kcc", context_attention=False, dimensional_attention=False,
                       spatiotemporal_attention=False, lost_pme=10.0)
        else:
            raise ValueError(f"unknown tracker profile {name!r}; choose one of {', '.join(PROFILES)}")
        return base.replace(**overrides) if overrides else base

    def replace(self, **changes) -> "TrackerConfig":
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise ValueError(f"unknown TrackerConfig field(s): {', '.join(unknown)}")
        return dataclasses.replace(self, **changes)


def parse_setting(setting: str) -> tuple[str, bool | int | float]:
    """'field=value' (eval's `@field=value`, the client's `--set`) as a TrackerConfig field and its value, read
    as the field's type: true / false, an integer or a number."""
    types = {f.name: f.type for f in dataclasses.fields(TrackerConfig) if f.type in ("bool", "int", "float")}
    field, _, text = setting.partition("=")
    text = text.strip()
    if field not in types or not text:
        raise ValueError(f"bad setting {setting!r}: use field=value with a numeric or true/false TrackerConfig field")
    kind = types[field]
    if kind == "bool":
        if text.lower() not in ("true", "false"):
            raise ValueError(f"{field} must be true or false, got {text!r}")
        return field, text.lower() == "true"
    try:
        return field, int(text) if kind == "int" else float(text)
    except ValueError:
        expected = "an integer" if kind == "int" else "a number"
        raise ValueError(f"{field} must be {expected}, got {text!r}") from None
