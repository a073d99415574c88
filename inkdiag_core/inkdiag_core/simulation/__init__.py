"""The fault simulators, one topic per module.

==============  =====================================================================
module          contents
==============  =====================================================================
``channels``    what both simulators share: :class:`DriveWaveform`, :class:`Spreads`,
                :data:`PHYSICAL_CONSTANTS`, the channel draw (:func:`draw_channels`
                -> :class:`ChannelDraw`)
``modal``       the exact modal response of the linear model
``sensor``      the sensor chain: gain and offset, white noise, ADC
``inputs``      the input checks both simulators share
``result``      :class:`SimulationResult`
``linear``      :func:`simulate`, :func:`simulate_nozzles`
``nonlinear``   :func:`simulate_nonlinear`, :class:`NonlinearTerms`
``datasets``    :func:`healthy_twin_frames`, :func:`healthy_twin_chunks`
``heldout``     held-out fault conditions, evaluation only: :func:`simulate_heldout`
``scenario``    a simulated head's faults over time: :class:`HeadScenario`,
                :func:`simulate_head`, :func:`defaults_on_head`
==============  =====================================================================

The public names of every module are re-exported here.
"""

from .channels import (
    PHYSICAL_CONSTANTS,
    ChannelDraw,
    DriveWaveform,
    Spreads,
    andrade_viscosity,
    bubble_compliance,
    draw_channels,
    observable_A,
)
from .datasets import healthy_twin_chunks, healthy_twin_frames
from .heldout import HELDOUT_CONDITIONS, HeldoutTraces, simulate_heldout
from .inputs import check_counts, check_positive_float, check_positive_int, check_severity, prepare_run
from .linear import simulate, simulate_nozzles
from .modal import class_max_frequency, cubic_roots, dominant_mode, modal_solution, nominal_rms, ramp_response
from .nonlinear import DEFAULT_COUPLING_M3_PER_V, NonlinearTerms, simulate_nonlinear
from .result import SimulationResult, empty_result
from .scenario import RANDOM_FAULT_CLASSES, HeadScenario, defaults_on_head, dried_class_of, simulate_head
from .sensor import adc_quantiser, draw_sensor, noise_std_for_snr, snr_db, white_noise

__all__ = [
    "PHYSICAL_CONSTANTS",
    "ChannelDraw",
    "DriveWaveform",
    "Spreads",
    "andrade_viscosity",
    "bubble_compliance",
    "draw_channels",
    "observable_A",
    "healthy_twin_chunks",
    "healthy_twin_frames",
    "HELDOUT_CONDITIONS",
    "HeldoutTraces",
    "simulate_heldout",
    "check_counts",
    "check_positive_float",
    "check_positive_int",
    "check_severity",
    "prepare_run",
    "simulate",
    "simulate_nozzles",
    "class_max_frequency",
    "cubic_roots",
    "dominant_mode",
    "modal_solution",
    "nominal_rms",
    "ramp_response",
    "DEFAULT_COUPLING_M3_PER_V",
    "NonlinearTerms",
    "simulate_nonlinear",
    "SimulationResult",
    "empty_result",
    "RANDOM_FAULT_CLASSES",
    "HeadScenario",
    "dried_class_of",
    "simulate_head",
    "defaults_on_head",
    "adc_quantiser",
    "draw_sensor",
    "noise_std_for_snr",
    "snr_db",
    "white_noise",
]
