"""The head a node runs for: its ``head_profile`` parameter and its loading, shared by the nodes."""

from __future__ import annotations

from inkdiag_core import HeadProfile

HEAD_PROFILE_PARAM = ("head_profile", "", "head profile YAML file; empty: the shipped default head", str, None)
"""The ``(name, default, description, type, range)`` entry every node's PARAMS has."""

SAMPLING_PARAMS = (
    ("n_samples", 0, "samples per trace of this head's frames (the model must be built for them); other frames "
     "are rejected. 0: the head profile's", int, (0, 65536)),
    ("sample_rate_hz", 0.0, "sample rate of this head's frames, Hz (the model must be built for it); other frames "
     "are rejected. 0: the head profile's", float, (0.0, 1e9)),
)
"""fdi's sampling parameters: 0 takes the head profile's (:func:`head_from_parameters`)."""


def load_fm_baselines(path: str, profile, logger):
    """The baselines of ``path`` with healthy f_m for fe (None: no path, or none with f_m, logged as an error).

    Raises ValueError (exit 2 at start, as a bad head_profile) for a file that does not load or is of another head."""
    import numpy as np
    from inkdiag_core import BaselineFileError, NozzleBaselines

    if not path:
        return None
    try:
        baselines = NozzleBaselines.load(path)
        baselines.check_head(profile)
    except BaselineFileError as exc:
        raise ValueError(f"baseline_path: {exc}") from None
    n_fm = 0 if baselines.fm is None else int((~np.isnan(baselines.fm)).sum())
    if not n_fm:
        logger.error(f"f_m baselines not used: {path} holds no healthy f_m (recorded with fm_frames:=0?)")
        return None
    logger.info(f"healthy f_m baselines of {n_fm} nozzles from {path}")
    return baselines


def head_from_parameters(config: dict, *, resample: bool = False) -> HeadProfile:
    """The complete head profile of ``config['head_profile']`` (empty: the shipped default head).

    Where ``config`` has ``sample_rate_hz`` / ``n_samples``, a value of 0 becomes the
    profile's (written back into ``config``); another value must be the profile's, or
    with ``resample=True`` samples the same head at that rate/length (the simulator).

    Raises
    ------
    ValueError
        The file does not load or is nominal (:class:`inkdiag_core.ProfileError`, whose
        message says to run ``inkdiag calibrate``), or the sampling parameters contradict
        it. Nodes let it stop them at start: one line, exit status 2.
    """
    path = config["head_profile"]
    head = HeadProfile.load(path) if path else HeadProfile.default()
    head.channel_params()  # a nominal profile: ProfileError
    change = {}
    for key in ("sample_rate_hz", "n_samples"):
        if key not in config:
            continue
        want = getattr(head, key)
        if not config[key]:
            config[key] = type(config[key])(want)
        elif config[key] != want:
            if not resample:
                raise ValueError(f"{key} is {config[key]:g} but head profile {head.name!r} ({path or 'the default head'}) "
                                 f"has {want:g}: leave {key} 0 to take the profile's")
            change[key] = config[key]
    return head.replace(**change) if change else head
