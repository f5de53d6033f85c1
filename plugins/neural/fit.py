"""``neural.fit``'s training: a per-texel encoder of the light responses to a latent code and a decoder shared by
every texel (code -> spherical-harmonic coefficients, or code + light features -> display value), trained jointly
by mini-batch Adam on a random sample of texels; then every texel is encoded."""
from __future__ import annotations

import numpy as np

from btforge.buffers import SampleStack
from btforge.numerics import texel_chunks

from .model import NeuralModel, harmonics, light_features, n_light_features
from .network import (Adam, decoder_backward, decoder_forward, init_layers, mlp_backward, mlp_forward,
                      pack_layers)

ENCODER_HIDDEN = (64, 64)  # the encoder is used only while fitting: small, it costs little next to the decoder
BATCH_TEXELS = 32          # texels per step, each with all its lights
LEARNING_RATE = 5e-3       # Adam's step at the start, decaying to 0 along a cosine


def texel_responses(stack: SampleStack, index: np.ndarray | slice) -> np.ndarray:
    """Display values ``[n, L, C]`` float32 of the texels ``index`` (into the flattened grid) of a one-view stack:
    an 8-bit capture's bytes / 255, a linear one's radiance sRGB-encoded."""
    from btforge.buffers import linear_to_srgb
    raw = np.asarray(stack.samples[0]).reshape(stack.n_light, -1, stack.n_channel)[:, index]
    values = raw / np.float32(255.0) if stack.encoding == "srgb8" else linear_to_srgb(raw)
    return np.ascontiguousarray(np.moveaxis(values.astype(np.float32), 0, 1))


def cosine_rate(step: int, total: int) -> float:
    return LEARNING_RATE * 0.5 * (1.0 + np.cos(np.pi * step / max(1, total)))


def jittered(rng: np.random.Generator, lights: np.ndarray, jitter: float) -> np.ndarray:
    """``lights`` each moved by a random offset of about ``jitter`` (radians) and renormalised, kept above the
    horizon: the decoder then sees a neighbourhood of each light, not the point alone."""
    if jitter == 0:
        return lights
    moved = lights + rng.normal(0.0, jitter, lights.shape)
    moved[:, 2] = np.abs(moved[:, 2])
    return moved / np.linalg.norm(moved, axis=1, keepdims=True)


class LightInputDecoder:
    """NeuralRTI's decoder: code and light features in, display value out, at every (texel, light) pair."""

    def __init__(self, rng, latent, hidden, layers, n_channel, lights, light_order, jitter):
        self.lights, self.light_order, self.jitter = lights, light_order, jitter
        self.layers = init_layers(rng, (latent + n_light_features(light_order),) + (hidden,) * layers + (n_channel,))

    def forward(self, rng, codes):
        self.codes = codes
        self.features = light_features(jittered(rng, self.lights, self.jitter), self.light_order)
        self.first, self.outs = decoder_forward(self.layers, codes, self.features)
        return self.outs[-1].reshape(len(codes), len(self.lights), -1)

    def backward(self, grad):
        return decoder_backward(self.layers, self.codes, self.features, self.first, self.outs,
                                grad.reshape(-1, grad.shape[2]))


class HarmonicsDecoder:
    """A decoder from the code to the texel's spherical-harmonic coefficients, run once per texel; the value at
    a light is their sum weighted by the harmonics there, so the function of the light stays of that order."""

    def __init__(self, rng, latent, hidden, layers, n_channel, lights, light_order, jitter):
        self.basis = harmonics(lights, light_order)
        self.n_coeff = self.basis.shape[1]
        self.layers = init_layers(rng, (latent,) + (hidden,) * layers + (self.n_coeff * n_channel,))

    def forward(self, rng, codes):
        self.outs = mlp_forward(self.layers, codes)
        return self.basis @ self.outs[-1].reshape(len(codes), self.n_coeff, -1)

    def backward(self, grad):
        return mlp_backward(self.layers, self.outs, (self.basis.T @ grad).reshape(len(grad), -1))


DECODERS = {"light": LightInputDecoder, "harmonics": HarmonicsDecoder}


def train(values: np.ndarray, lights: np.ndarray, decoder_kind: str, light_order: int, *, latent: int, hidden: int,
          layers: int, epochs: int, jitter: float, seed: int):
    """Encoder and decoder trained on ``values [n, L, C]`` at unit ``lights [L, 3]``, the per-light mean the
    encoder's input is taken from, and the final epoch's mean squared error."""
    rng = np.random.default_rng(seed)
    n, n_light, n_channel = values.shape
    mean = values.mean(axis=0)
    encoder = init_layers(rng, (n_light * n_channel,) + ENCODER_HIDDEN + (latent,))
    decoder = DECODERS[decoder_kind](rng, latent, hidden, layers, n_channel, np.asarray(lights, np.float64),
                                     light_order, jitter)
    adam = Adam([a for layer in encoder + decoder.layers for a in layer])
    per_epoch = -(-n // BATCH_TEXELS)
    total, mse = epochs * per_epoch, 0.0
    for epoch in range(epochs):
        order, loss = rng.permutation(n), 0.0
        for step in range(per_epoch):
            target = values[np.sort(order[step * BATCH_TEXELS:(step + 1) * BATCH_TEXELS])]
            enc_outs = mlp_forward(encoder, (target - mean).reshape(len(target), -1))
            error = decoder.forward(rng, enc_outs[-1]) - target
            loss += float(np.vdot(error, error)) / error.size
            grad_dec, grad_codes = decoder.backward(error * np.float32(2.0 / error.size))
            grad_enc, _ = mlp_backward(encoder, enc_outs, grad_codes)
            adam.step([g for layer in grad_enc + grad_dec for g in layer], cosine_rate(epoch * per_epoch + step, total))
        mse = loss / per_epoch
    return encoder, decoder.layers, mean, mse


def encode(stack: SampleStack, encoder, mean: np.ndarray) -> np.ndarray:
    """Latent codes ``[H * W, K]`` float32 of every texel, by bands of texels."""
    n_texel = stack.height * stack.width
    codes = np.empty((n_texel, encoder[-1][0].shape[1]), np.float32)
    for chunk in texel_chunks(n_texel, 16 * stack.n_light * stack.n_channel):
        values = texel_responses(stack, chunk) - mean
        codes[chunk] = mlp_forward(encoder, values.reshape(len(values), -1))[-1]
    return codes


def build_model(codes: np.ndarray, decoder_layers, light_order: int, decoder: str, channels) -> NeuralModel:
    sizes = tuple(w.shape[0] for w, _ in decoder_layers) + (decoder_layers[-1][0].shape[1],)
    return NeuralModel(codes, pack_layers(decoder_layers), sizes, light_order, decoder, tuple(channels))


def fit_neural(stack: SampleStack, decoder: str, latent: int, hidden: int, layers: int, light_order: int,
               epochs: int, texels: int, seed: int, jitter: float = 0.0) -> tuple[NeuralModel, dict]:
    """The model of a one-view stack and ``{"train_psnr_db", "texels"}`` (the training sample's last epoch)."""
    rng = np.random.default_rng(seed)
    n_texel = stack.height * stack.width
    sample = np.sort(rng.choice(n_texel, min(texels, n_texel), replace=False))
    encoder, decoder_layers, mean, mse = train(texel_responses(stack, sample), np.asarray(stack.lights, np.float64),
                                               decoder, light_order, latent=latent, hidden=hidden, layers=layers,
                                               epochs=epochs, jitter=jitter, seed=int(rng.integers(2 ** 31)))
    codes = encode(stack, encoder, mean).reshape(stack.height, stack.width, latent)
    model = build_model(codes, decoder_layers, light_order, decoder, stack.channels)
    psnr = float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)
    return model, {"train_psnr_db": round(psnr, 2), "texels": len(sample)}
