"""Training-time augmentation of batches of frames (torch, on the training device): mirror with the yaw rate's sign,
colour jitter, blur and the noise injector's salt and pepper, drawn from a seeded generator so a run repeats."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from brains.nets.preprocess import MAX_PIXEL

_LUMA = (0.299, 0.587, 0.114)  # sums to 1


def to_unit_float(frames: torch.Tensor) -> torch.Tensor:
    """uint8 frames (B, T, H, W, 3) as gathered -> float32 (B, T, 3, H, W) in [0, 1], contiguous.

    Channels go first while still uint8: float ops on the permuted (channels-last strided) tensor are several
    times slower."""
    return frames.permute(0, 1, 4, 2, 3).contiguous().float().div_(MAX_PIXEL)


def augment_batch(
    frames: torch.Tensor,
    labels: torch.Tensor,
    generator: torch.Generator,
    *,
    mirror_p: float = 0.5,
    jitter: float = 0.2,
    blur_p: float = 0.2,
    noise_max: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random training augmentation, one parameter set per sample shared by all its frames.

    frames: uint8 (B, T, H, W, 3) RGB; labels: (B, 2) physical [v m/s, w rad/s]. Returns float32 (B, T, 3, H, W)
    in [0, 1] and the labels. Mirror left-right with w -> -w (probability mirror_p); brightness, contrast and
    saturation factors uniform in [1 - jitter, 1 + jitter]; Gaussian blur (probability blur_p, sigma 0.5..1.5 px,
    one sigma per batch); with ``noise_max`` > 0, salt and pepper of density uniform in [0, noise_max] on half the
    samples (:func:`salt_pepper_resized`). The same random numbers are drawn whatever the data, so the generator
    advances identically every batch (resume stays exact).
    """
    draws = torch.rand(5, frames.shape[0], generator=generator).to(frames.device)
    sigma = 0.5 + float(torch.rand(1, generator=generator))
    frames, labels = mirror(frames, labels, draws[0] < mirror_p)  # on uint8: 4x less memory to move
    x = colour_jitter(to_unit_float(frames), *(1 - jitter + 2 * jitter * draws[1:4]))
    blurred = (draws[4] < blur_p).nonzero().squeeze(1)
    if len(blurred):  # x is a fresh tensor here (colour_jitter), so writing into it is safe
        x[blurred] = gaussian_blur(x[blurred], sigma)
    if noise_max > 0:  # drawn only when asked for, so runs without it keep their random sequence
        density = torch.rand(frames.shape[0], generator=generator) * noise_max
        density = torch.where(torch.rand(frames.shape[0], generator=generator) < 0.5, density, 0.0)
        x = salt_pepper_resized(x, density.to(x.device), generator)
    return x, labels


# Camera pixels averaged into one network pixel: 320x240 cropped to its lower half and resized to 100x50 averages
# 3.2 x 2.4; the noise injector's salt and pepper is per camera pixel, so the network sees it averaged that way.
NOISE_SUBPIXELS = 8


def salt_pepper_resized(x: torch.Tensor, density: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Salt and pepper noise as it looks after an area resize: of each pixel's ``NOISE_SUBPIXELS`` camera pixels,
    Binomial(n, density) are replaced, half of them (binomially) by white and the rest by black; independent per
    frame and pixel, the same across a pixel's channels (the injector replaces whole pixels).

    x: (B, T, 3, H, W) in [0, 1]; density: (B,) per sample, 0 = untouched.
    """
    b, t, _, h, w = x.shape
    n = float(NOISE_SUBPIXELS)
    counts = torch.full((b, t, 1, h, w), n)
    replaced = torch.binomial(counts, density.view(-1, 1, 1, 1, 1).expand(b, t, 1, h, w).cpu(), generator=generator)
    white = torch.binomial(replaced, torch.full_like(replaced, 0.5), generator=generator)
    replaced, white = replaced.to(x.device), white.to(x.device)
    return (x * (n - replaced) + white) / n


def mirror(frames: torch.Tensor, labels: torch.Tensor, flip: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Left-right mirror of the samples where ``flip`` (B,) bool is set, with their yaw rate negated (mirroring
    the road turns w into -w). frames: (B, T, H, W, C), width second to last; labels: (B, 2) physical [v, w]."""
    chosen = flip.nonzero().squeeze(1)
    frames = frames.clone()
    frames[chosen] = frames[chosen].flip(-2)  # only the chosen half: ~2x faster than a torch.where over all
    w = torch.where(flip, -labels[:, 1], labels[:, 1])
    return frames, torch.stack([labels[:, 0], w], dim=1)


def colour_jitter(
    x: torch.Tensor, brightness: torch.Tensor, contrast: torch.Tensor, saturation: torch.Tensor
) -> torch.Tensor:
    """x (B, T, 3, H, W) RGB in [0, 1]; factors (B,), 1 = unchanged. Brightness scales x; contrast scales about the
    image's mean grey; saturation scales about each pixel's grey; clamped to [0, 1].

    Composed in closed form, one pass over the pixels instead of a dozen (grey is linear, luma sums to 1):
    x' = s·c·b·x + (1-s)·c·b·grey(x) + (1-c)·b·mean_grey(x).
    """
    per_sample = (-1, 1, 1, 1)
    grey = (x[:, :, 0] * _LUMA[0]).add_(x[:, :, 1], alpha=_LUMA[1]).add_(x[:, :, 2], alpha=_LUMA[2])  # (B, T, H, W)
    scale = brightness * contrast
    offset = ((1 - saturation) * scale).view(per_sample) * grey + ((1 - contrast) * brightness).view(
        per_sample
    ) * grey.mean((-2, -1), keepdim=True)
    return torch.addcmul(offset.unsqueeze(2), x, (saturation * scale).view(-1, 1, 1, 1, 1)).clamp_(0.0, 1.0)


def gaussian_blur(x: torch.Tensor, sigma: float, radius: int = 2) -> torch.Tensor:
    """Separable Gaussian blur over the last two dims (H, W) of x, edges replicated; sigma in pixels.

    Shifted-slice sums: for a 5-tap kernel this is several times faster on CPU than a depthwise convolution."""
    height, width = x.shape[-2:]
    taps = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-(taps**2) / (2 * sigma**2))
    weights: list[float] = (kernel / kernel.sum()).tolist()
    padded = F.pad(x.reshape(-1, 1, height, width), (radius,) * 4, mode="replicate")
    # A tensor zero to start from (sum's default is the int 0, which types the sum as Tensor | int); 0.0 + v is
    # 0 + v for every float, so the result is bit for bit what it was.
    zero = x.new_zeros(())
    rows = sum((k * padded[..., i : i + width] for i, k in enumerate(weights)), zero)
    return sum((k * rows[..., i : i + height, :] for i, k in enumerate(weights)), zero).view(x.shape)
