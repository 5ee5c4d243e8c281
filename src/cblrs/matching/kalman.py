"""A constant-velocity Kalman filter on the ground plane, vectorised over tracks.

State per track: ``(x, y, vx, vy)`` in metres and metres per second; covariance (4, 4).
Process noise is white acceleration with standard deviation ``acceleration_sigma`` (m/s^2),
the usual continuous-time discretisation. Measurements are positions ``(x, y)`` with either
an isotropic variance per measurement (square metres) or a full (2, 2) covariance (a
camera's ground error is elongated along its viewing ray). Everything takes arrays over T
tracks, so a frame costs a handful of numpy calls whatever the number of tracks.

For targets that mostly move steadily but sometimes turn or stop, the interacting
multiple-model (IMM) functions run several such filters per track with different
accelerations and weigh them by how well each predicted the measurements.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def predict(
    state: FloatArray, covariance: FloatArray, dt: float, acceleration_sigma: float | FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Propagate states by ``dt`` seconds.

    Args:
        state: (T, 4) float64.
        covariance: (T, 4, 4) float64.
        dt: seconds (>= 0), the same for all tracks.
        acceleration_sigma: white-noise acceleration, m/s^2, scalar or (T,) per track.

    Returns:
        The predicted ``(state, covariance)``, new arrays.
    """
    if dt <= 0.0 or len(state) == 0:
        return state.copy(), covariance.copy()
    transition, unit_noise = _motion_matrices(float(dt))
    state = state @ transition.T
    variance = np.asarray(acceleration_sigma, np.float64) ** 2
    if variance.ndim == 0:
        variance = np.full(len(state), variance)
    covariance = transition @ covariance @ transition.T + variance[:, None, None] * unit_noise
    return state, covariance


def _motion_matrices(dt: float) -> tuple[FloatArray, FloatArray]:
    """The transition and unit process noise over ``dt`` (read only): kept for the last few
    steps, since a stream's steps repeat (its frame period)."""
    cached = _MOTION_CACHE.get(dt)
    if cached is not None:
        return cached
    transition = np.eye(4)
    transition[0, 2] = transition[1, 3] = dt
    # The same block on (x, vx) and (y, vy), written element by element: np.ix_ and
    # broadcast_to cost more than the arithmetic, several times a window.
    unit_noise = np.zeros((4, 4))
    unit_noise[0, 0] = unit_noise[1, 1] = dt**4 / 4
    unit_noise[0, 2] = unit_noise[2, 0] = unit_noise[1, 3] = unit_noise[3, 1] = dt**3 / 2
    unit_noise[2, 2] = unit_noise[3, 3] = dt**2
    transition.flags.writeable = unit_noise.flags.writeable = False
    if len(_MOTION_CACHE) >= _MOTION_CACHE_SIZE:
        del _MOTION_CACHE[next(iter(_MOTION_CACHE))]
    _MOTION_CACHE[dt] = transition, unit_noise
    return transition, unit_noise


_MOTION_CACHE: dict[float, tuple[FloatArray, FloatArray]] = {}
_MOTION_CACHE_SIZE = 16
_SWITCH_CACHE: dict[tuple[float, bytes], FloatArray] = {}  # transition_matrix, read only


def measurement_matrices(measurement_variance: FloatArray | float, count: int) -> FloatArray:
    """(count, 2, 2) measurement covariances from a scalar, (count,) or (count, 2, 2) input.

    Scalars and (count,) arrays are isotropic variances, square metres.
    """
    variance = np.asarray(measurement_variance, np.float64)
    if variance.ndim == 3:
        return variance
    matrices = np.zeros((count, 2, 2))
    matrices[:, 0, 0] = matrices[:, 1, 1] = np.broadcast_to(variance, (count,))
    return matrices


def innovation_covariance(
    covariance: FloatArray, measurement_variance: FloatArray | float
) -> FloatArray:
    """(T, 2, 2) covariance of the position innovation, ``P_xy + R``.

    Args:
        covariance: (T, 4, 4) state covariances.
        measurement_variance: scalar or (T,) isotropic variances (square metres), or (T, 2, 2)
            measurement covariances.
    """
    return covariance[:, :2, :2] + measurement_matrices(measurement_variance, len(covariance))


def inverse_2x2(matrices: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Closed-form inverses and determinants of (T, 2, 2) matrices."""
    a, b = matrices[:, 0, 0], matrices[:, 0, 1]
    c, d = matrices[:, 1, 0], matrices[:, 1, 1]
    determinant = a * d - b * c
    # (d, -b, -c, a) / determinant, element by element as written out, in one division: one
    # gather and one negation cost less than stacking four columns.
    inverse = matrices.reshape(len(matrices), 4)[:, _ADJUGATE_ORDER]
    np.negative(inverse[:, 1:3], out=inverse[:, 1:3])
    inverse /= determinant[:, None]
    return inverse.reshape(matrices.shape), determinant


_ADJUGATE_ORDER = np.array([3, 1, 2, 0])  # (d, b, c, a) of a row-major (a, b, c, d)


def update(
    state: FloatArray,
    covariance: FloatArray,
    measurement_xy: FloatArray,
    measurement_variance: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Kalman update with one position measurement per track.

    Args:
        state: (T, 4); covariance: (T, 4, 4).
        measurement_xy: (T, 2) metres.
        measurement_variance: (T,) isotropic variances, square metres, or (T, 2, 2)
            covariances.

    Returns:
        The updated ``(state, covariance)``, new arrays.
    """
    if len(state) == 0:
        return state.copy(), covariance.copy()
    innovation_inverse, _ = inverse_2x2(innovation_covariance(covariance, measurement_variance))
    return _update(state, covariance, measurement_xy - state[:, :2], innovation_inverse)


def _update(
    state: FloatArray,
    covariance: FloatArray,
    residual: FloatArray,
    innovation_inverse: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`update` given the position residual and the inverse innovation covariance."""
    gain = covariance[:, :, :2] @ innovation_inverse  # (T, 4, 2)
    # gain @ residual written out (two terms: the same sum as any einsum or loop).
    state = state + (gain[:, :, 0] * residual[:, :1] + gain[:, :, 1] * residual[:, 1:])
    # Joseph-free form is fine here: the gain is optimal and the matrices are 4 x 4.
    covariance = covariance - gain @ covariance[:, :2, :]
    covariance = 0.5 * (covariance + covariance.transpose(0, 2, 1))
    return state, covariance


def initial_covariance(
    count: int, position_variance: FloatArray | float, velocity_sigma: FloatArray | float
) -> FloatArray:
    """(count, 4, 4) covariance of newly born tracks: measured position, unknown velocity.

    ``position_variance`` is a scalar or (count,) isotropic variance, or (count, 2, 2);
    ``velocity_sigma`` a scalar or (count,) standard deviation of each velocity component.
    """
    covariance = np.zeros((count, 4, 4))
    covariance[:, :2, :2] = measurement_matrices(position_variance, count)
    covariance[:, 2, 2] = covariance[:, 3, 3] = velocity_sigma**2
    return covariance


# ---------------------------------------------------------------- interacting multiple models
# M constant-velocity models that differ only in their white-noise acceleration (a person
# walking steadily, the same person turning or stopping), switching as a Markov chain whose
# mean time in each model is its sojourn time. States are (T, M, 4), covariances
# (T, M, 4, 4), model probabilities (T, M).


def transition_matrix(dt: float, sojourn_s: FloatArray) -> FloatArray:
    """(M, M) probabilities of switching from model i (row) to j (column) within ``dt``.

    A model is left with rate ``1 / sojourn``, for the others in proportion to their own
    sojourn times (with two models: for the other one).
    """
    sojourn = np.asarray(sojourn_s, np.float64)
    count = len(sojourn)
    stay = np.exp(-dt / sojourn)
    if count == 1:
        return np.ones((1, 1))
    share = sojourn[None, :] * (1.0 - np.eye(count))
    share /= share.sum(axis=1, keepdims=True)
    return np.diag(stay) + (1.0 - stay)[:, None] * share


def stationary_probability(sojourn_s: FloatArray) -> FloatArray:
    """(M,) long-run share of time in each model (proportional to its sojourn time)."""
    sojourn = np.asarray(sojourn_s, np.float64)
    return sojourn / sojourn.sum()


def combine(
    mode_state: FloatArray, mode_covariance: FloatArray, probability: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Moment-matched (T, 4) state and (T, 4, 4) covariance of the model mixture."""
    state = np.einsum("tm,tmi->ti", probability, mode_state)
    spread = mode_state - state[:, None, :]
    covariance = np.einsum(
        "tm,tmij->tij",
        probability,
        mode_covariance + spread[:, :, :, None] * spread[:, :, None, :],
    )
    return state, covariance


def predict_models(
    mode_state: FloatArray,
    mode_covariance: FloatArray,
    probability: FloatArray,
    dt: float,
    acceleration_sigma: FloatArray,
    sojourn_s: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Interaction (mixing) and prediction of every model by ``dt`` seconds.

    Args:
        mode_state: (T, M, 4); mode_covariance: (T, M, 4, 4); probability: (T, M).
        dt: seconds (>= 0).
        acceleration_sigma: (T, M) white-noise acceleration of each track's models, m/s^2.
        sojourn_s: (M,) mean time spent in each model, seconds.

    Returns:
        The predicted ``(mode_state, mode_covariance, probability)``, new arrays.
    """
    if dt <= 0.0 or len(mode_state) == 0:
        return mode_state.copy(), mode_covariance.copy(), probability.copy()
    switch = _switch_matrix(float(dt), sojourn_s)
    predicted = probability @ switch  # (T, M)
    weight = (
        switch[None] * probability[:, :, None] / np.maximum(predicted[:, None, :], 1e-300)
    )  # (T, from i, to j)
    # Sums over the source model written out in model order: bit for bit what a generic
    # einsum gives, at a fraction of its cost on these small axes.
    models = mode_state.shape[1]
    mixed = weight[:, 0, :, None] * mode_state[:, :1]  # (T, j, 4)
    for source in range(1, models):
        mixed += weight[:, source, :, None] * mode_state[:, source : source + 1]
    spread = mode_state[:, :, None, :] - mixed[:, None, :, :]  # (T, i, j, 4)
    term = np.einsum("...k,...l->...kl", spread, spread)
    term += mode_covariance[:, :, None]
    term *= weight[:, :, :, None, None]
    mixed_covariance = term[:, 0]
    for source in range(1, models):
        mixed_covariance += term[:, source]
    # Every model's prediction in one go (the same products as one model at a time).
    transition, unit_noise = _motion_matrices(float(dt))
    new_state = (mixed.reshape(-1, 4) @ transition.T).reshape(mixed.shape)
    variance = np.asarray(acceleration_sigma, np.float64) ** 2
    new_covariance = _propagate(mixed_covariance, transition)
    new_covariance += variance[:, :, None, None] * unit_noise
    return new_state, new_covariance, predicted


def _propagate(covariance: FloatArray, transition: FloatArray) -> FloatArray:
    """``transition @ covariance @ transition.T`` for (..., 4, 4) covariances, as two 2-D
    products over all the rows at once (a stacked matmul makes one small product per matrix,
    several times slower); the same products, so the same bits."""
    shape = covariance.shape
    # Rows of (F C)^T are the rows of C^T times F^T.
    left = covariance.swapaxes(-1, -2).reshape(-1, 4) @ transition.T
    left = left.reshape(shape).swapaxes(-1, -2).reshape(-1, 4)
    return (left @ transition.T).reshape(shape)


def _switch_matrix(dt: float, sojourn_s: FloatArray) -> FloatArray:
    """:func:`transition_matrix`, kept for the last few steps (a stream's steps repeat)."""
    sojourn = np.asarray(sojourn_s, np.float64)
    key = (dt, sojourn.tobytes())
    switch = _SWITCH_CACHE.get(key)
    if switch is None:
        switch = transition_matrix(dt, sojourn)
        switch.flags.writeable = False
        if len(_SWITCH_CACHE) >= _MOTION_CACHE_SIZE:
            del _SWITCH_CACHE[next(iter(_SWITCH_CACHE))]
        _SWITCH_CACHE[key] = switch
    return switch


def update_models(
    mode_state: FloatArray,
    mode_covariance: FloatArray,
    probability: FloatArray,
    measurement_xy: FloatArray,
    measurement_variance: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Update every model with one position per track and re-weigh the models.

    Args:
        mode_state: (T, M, 4); mode_covariance: (T, M, 4, 4); probability: (T, M).
        measurement_xy: (T, 2) metres.
        measurement_variance: (T,) isotropic variances or (T, 2, 2) covariances.

    Returns:
        The updated ``(mode_state, mode_covariance, probability)``, new arrays. Each model's
        probability is multiplied by the likelihood of the measurement under it.
    """
    return update_models_likelihood(
        mode_state, mode_covariance, probability, measurement_xy, measurement_variance)[:3]


def update_models_likelihood(
    mode_state: FloatArray,
    mode_covariance: FloatArray,
    probability: FloatArray,
    measurement_xy: FloatArray,
    measurement_variance: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`update_models`, and the (T, M) log-likelihood of each measurement under each
    model before the update (``-(r' S^-1 r + log det S) / 2``, constant dropped)."""
    count, models = mode_state.shape[:2]
    if count == 0:
        return (mode_state.copy(), mode_covariance.copy(), probability.copy(),
                np.zeros((0, models)))
    # All models of all tracks as one stack of T * M filters.
    measurement = measurement_matrices(measurement_variance, count)
    innovation = mode_covariance[:, :, :2, :2] + measurement[:, None]
    inverse, determinant = inverse_2x2(innovation.reshape(-1, 2, 2))
    residual = (measurement_xy[:, None, :] - mode_state[:, :, :2]).reshape(-1, 2)
    # residual' inverse residual, the terms in the order einsum("ti,tij,tj->t") sums them.
    r0, r1 = residual[:, 0], residual[:, 1]
    flat = inverse.reshape(-1, 4)
    squared = r0 * flat[:, 0] * r0 + r0 * flat[:, 1] * r1 + r1 * flat[:, 2] * r0
    squared += r1 * flat[:, 3] * r1
    likelihood = (-0.5 * (squared + np.log(determinant))).reshape(count, models)
    new_state, new_covariance = _update(
        mode_state.reshape(-1, 4), mode_covariance.reshape(-1, 4, 4), residual, inverse
    )
    new_state = new_state.reshape(mode_state.shape)
    new_covariance = new_covariance.reshape(mode_covariance.shape)
    log_likelihood = likelihood - likelihood.max(axis=1, keepdims=True)
    weighted = probability * np.exp(log_likelihood)
    total = weighted.sum(axis=1, keepdims=True)
    new_probability = np.where(total > 0, weighted / np.where(total > 0, total, 1.0), probability)
    return new_state, new_covariance, new_probability, likelihood
