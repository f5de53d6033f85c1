"""The networks of ``neural.fit`` in NumPy: multilayer perceptrons with ELU between layers, their gradients, and
the Adam optimiser.  Float32 throughout; run under a single-threaded BLAS, so results are reproducible."""
from __future__ import annotations

import numpy as np


def elu(x: np.ndarray) -> np.ndarray:
    """ELU, max(x, 0) + exp(min(x, 0)) - 1: x above 0, exp(x) - 1 below, and exp never sees a large x."""
    out = np.expm1(np.minimum(x, 0))
    out += np.maximum(x, 0)
    return out


def elu_slope(y: np.ndarray) -> np.ndarray:
    """The slope of ELU written with its output ``y``: 1 where the input was positive, else exp(x) = y + 1."""
    out = np.minimum(y, 0)
    out += 1
    return out


def init_layers(rng: np.random.Generator, sizes) -> list[list[np.ndarray]]:
    """``[W, b]`` per layer: Glorot-uniform weights, zero biases, float32."""
    layers = []
    for n_in, n_out in zip(sizes[:-1], sizes[1:]):
        limit = np.sqrt(6.0 / (n_in + n_out))
        layers.append([rng.uniform(-limit, limit, (n_in, n_out)).astype(np.float32), np.zeros(n_out, np.float32)])
    return layers


def pack_layers(layers) -> np.ndarray:
    """Every layer's weights then biases, flattened into one float32 array."""
    return np.concatenate([a.reshape(-1) for layer in layers for a in layer]).astype(np.float32)


def unpack_layers(flat: np.ndarray, sizes) -> list[list[np.ndarray]]:
    layers, at = [], 0
    for n_in, n_out in zip(sizes[:-1], sizes[1:]):
        w = flat[at:at + n_in * n_out].reshape(n_in, n_out)
        at += n_in * n_out
        layers.append([w, flat[at:at + n_out]])
        at += n_out
    return layers


def decoder_layers_forward(layers, hidden: np.ndarray) -> np.ndarray:
    """The layers after the first, from its activations: ELU between them, linear output."""
    for i, (w, b) in enumerate(layers):
        hidden = hidden @ w + b
        if i < len(layers) - 1:
            hidden = elu(hidden)
    return hidden


def mlp_forward(layers, x: np.ndarray) -> list[np.ndarray]:
    """The input and every layer's output (ELU between layers, linear output), kept for the backward pass."""
    outs = [x]
    for i, (w, b) in enumerate(layers):
        z = outs[-1] @ w + b
        outs.append(z if i == len(layers) - 1 else elu(z))
    return outs


def mlp_backward(layers, outs, grad: np.ndarray):
    """``[dW, db]`` per layer and the gradient at the input, for the output gradient ``grad``."""
    grads = [None] * len(layers)
    for i in range(len(layers) - 1, -1, -1):
        if i < len(layers) - 1:
            grad = grad * elu_slope(outs[i + 1])
        grads[i] = [outs[i].T @ grad, grad.sum(axis=0)]
        grad = grad @ layers[i][0].T
    return grads, grad


def decoder_forward(layers, codes: np.ndarray, features: np.ndarray):
    """The decoder at every (texel, light) pair of ``codes [B, K]`` and ``features [L, F]``: the first layer's
    activations ``[B * L, H]`` and the outputs of the rest (last ``[B * L, C]``).  The first layer splits into a
    part per texel and a part per light, summed by broadcasting, so it costs B + L products, not B x L."""
    w1, b1 = layers[0]
    k = codes.shape[1]
    first = elu((codes @ w1[:k])[:, None, :] + (features @ w1[k:] + b1)[None, :, :]).reshape(-1, w1.shape[1])
    return first, mlp_forward(layers[1:], first)


def decoder_backward(layers, codes, features, first, outs, grad_out):
    """Gradients of the decoder's layers and of the codes for the output gradient ``grad_out [B * L, C]``."""
    n_texel, n_light, k = codes.shape[0], features.shape[0], codes.shape[1]
    grads, grad_first = mlp_backward(layers[1:], outs, grad_out)
    grad_z = (grad_first * elu_slope(first)).reshape(n_texel, n_light, -1)
    per_texel, per_light = grad_z.sum(axis=1), grad_z.sum(axis=0)
    grad_w1 = np.concatenate([codes.T @ per_texel, features.T @ per_light], axis=0)
    return [[grad_w1, per_light.sum(axis=0)]] + grads, per_texel @ layers[0][0][:k].T


class Adam:
    """Adam (Kingma & Ba 2015) over a list of float32 arrays, updated in place; gradients are first scaled to a
    global norm of at most ``clip``, so a step stays bounded whatever the data."""

    def __init__(self, params: list[np.ndarray], clip: float = 1.0, beta1: float = 0.9, beta2: float = 0.999,
                 eps: float = 1e-8):
        self.params, self.clip, self.beta1, self.beta2, self.eps, self.t = params, clip, beta1, beta2, eps, 0
        self.m = [np.zeros_like(p) for p in params]
        self.v = [np.zeros_like(p) for p in params]

    def step(self, grads: list[np.ndarray], lr: float) -> None:
        self.t += 1
        norm = float(np.sqrt(sum(float(np.vdot(g, g)) for g in grads)))
        scale = np.float32(min(1.0, self.clip / norm) if norm > 0 else 1.0)
        c1, c2 = 1 - self.beta1 ** self.t, 1 - self.beta2 ** self.t
        for p, g, m, v in zip(self.params, grads, self.m, self.v):
            g = g * scale
            m *= np.float32(self.beta1)
            m += np.float32(1 - self.beta1) * g
            v *= np.float32(self.beta2)
            v += np.float32(1 - self.beta2) * g * g
            p -= np.float32(lr / c1) * m / (np.sqrt(v / np.float32(c2)) + np.float32(self.eps))
