"""Audio front ends, Audio Encoder and smoother against outside references and hand cases."""

import numpy as np
import pytest
import python_speech_features as psf
import scipy.fft
import scipy.signal
import torch

from lmgs.audio import (
    AudioNet,
    AudioSmoother,
    compute_features,
    frame_count,
    frame_windows,
    frontend_from_array,
    load_waveform,
    log_mel_spectrogram,
    mel_filterbank,
    power_spectrogram,
    waveform_features,
)
from lmgs.config import AudioConfig
from lmgs.errors import InputError

SR = 16000


def _speechlike(n, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / SR
    x = 0.3 * np.sin(2 * np.pi * 220 * t) * (1 + np.sin(2 * np.pi * 3 * t)) + 0.05 * rng.standard_normal(n)
    return x.astype(np.float32)


def test_power_spectrum_matches_python_speech_features():
    x = _speechlike(8000).astype(np.float64)
    hann = lambda n: scipy.signal.get_window("hann", n)  # noqa: E731
    frames = psf.sigproc.framesig(x, 400, 160, winfunc=hann)
    ref = psf.sigproc.powspec(frames, 512)
    ours = power_spectrogram(x, 400, 160, 512)
    assert ours.shape[0] == 1 + (8000 - 400) // 160
    np.testing.assert_allclose(ours, ref[: ours.shape[0]], rtol=1e-9, atol=1e-12)


def test_log_mel_matches_direct_definition():
    # the HTK-mel triangle definition written out independently, per filter and per bin
    x = _speechlike(6400, seed=1).astype(np.float64)
    n_mels, n_fft = 40, 512
    mel = lambda f: 2595 * np.log10(1 + f / 700)  # noqa: E731
    imel = lambda m: 700 * (10 ** (m / 2595) - 1)  # noqa: E731
    pts = imel(np.linspace(mel(0), mel(8000), n_mels + 2))
    fb = np.zeros((n_mels, n_fft // 2 + 1))
    for m in range(n_mels):
        for k in range(n_fft // 2 + 1):
            f = k * SR / n_fft
            if pts[m] <= f <= pts[m + 1]:
                fb[m, k] = (f - pts[m]) / (pts[m + 1] - pts[m])
            elif pts[m + 1] < f <= pts[m + 2]:
                fb[m, k] = (pts[m + 2] - f) / (pts[m + 2] - pts[m + 1])
    _, _, Z = scipy.signal.stft(x, fs=SR, window="hann", nperseg=400, noverlap=240, nfft=n_fft, boundary=None, padded=False)
    # scipy scales the STFT by 1/sum(window); undo it and apply the 1/NFFT power convention
    win_sum = scipy.signal.get_window("hann", 400).sum()
    P = (np.abs(Z.T * win_sum) ** 2) / n_fft
    ref = np.log(np.maximum(P @ fb.T, 1e-10))
    ours = log_mel_spectrogram(x, n_mels=n_mels)
    assert ours.shape == ref.shape
    np.testing.assert_allclose(ours, ref, rtol=1e-7, atol=1e-7)


def test_mel_filter_of_a_tone_peaks_at_its_band():
    fb = mel_filterbank(80, 512)
    centres = 700 * (10 ** (np.linspace(0, 2595 * np.log10(1 + 8000 / 700), 82)[1:-1] / 2595) - 1)
    t = np.arange(SR) / SR
    for f0 in (300.0, 1000.0, 3000.0):
        lm = log_mel_spectrogram(np.sin(2 * np.pi * f0 * t))
        band = int(np.argmax(lm.mean(0)))
        assert abs(centres[band] - f0) <= 0.5 * (centres[min(band + 1, 79)] - centres[max(band - 1, 0)])
    # adjacent unnormalised triangles add up to 1 between the first and last centre
    k = np.arange(257) * SR / 512
    inside = (k >= centres[0]) & (k <= centres[-1])
    np.testing.assert_allclose(fb.sum(0)[inside], 1.0, atol=1e-9)


@pytest.mark.parametrize("n_samples,expected", [(0, 0), (639, 0), (640, 1), (1279, 1), (1280, 2), (16000, 25), (16639, 25)])
def test_frame_count_is_floor_of_samples_over_640(n_samples, expected):
    assert frame_count(n_samples) == expected
    f = waveform_features(np.zeros(n_samples, np.float32))
    assert f.shape == (expected, 16, 80)


def test_tail_padding_and_short_audio():
    x = _speechlike(1000)  # shorter than two frames
    f = waveform_features(x, n_frames=3)
    assert f.shape == (3, 16, 80)
    assert np.isfinite(f).all()
    # the third frame (samples 1280..1919) lies beyond the audio: its centre steps are silent
    assert np.allclose(f[2, 6:10], np.log(1e-10))
    assert f[0, 6:10].max() > -10  # while frame 0 hears the signal


def test_silence_and_clipping_give_finite_features():
    silent = waveform_features(np.zeros(4000, np.float32))
    assert np.isfinite(silent).all() and np.allclose(silent, np.log(1e-10))
    clipped = load_waveform(np.clip(5 * _speechlike(4000), -1, 1), SR)
    over = load_waveform(3.0 * _speechlike(4000), SR)  # beyond full scale: clipped, not refused
    assert over.max() <= 1.0 and over.min() >= -1.0
    for kind in ("logmel", "mfcc"):
        assert np.isfinite(waveform_features(clipped, kind)).all()


def test_mfcc_is_dct_of_log_mel():
    x = _speechlike(3200, seed=2)
    lm = waveform_features(x, "logmel", n_mels=40)
    mf = waveform_features(x, "mfcc", n_mels=40, n_mfcc=13)
    ref = scipy.fft.dct(lm.astype(np.float64), type=2, norm="ortho", axis=-1)[..., :13]
    np.testing.assert_allclose(mf, ref, rtol=1e-4, atol=1e-3)


def test_resampling_44k_stereo_keeps_frequency():
    sr, f0 = 44100, 1000.0
    t = np.arange(int(sr * 0.5)) / sr
    stereo = np.stack([0.5 * np.sin(2 * np.pi * f0 * t), 0.5 * np.sin(2 * np.pi * f0 * t)], axis=1)
    y = load_waveform(stereo, sr)
    assert y.dtype == np.float32 and y.ndim == 1
    assert abs(len(y) - 8000) <= 1
    spec = np.abs(np.fft.rfft(y * np.hanning(len(y))))
    peak = np.argmax(spec) * SR / len(y)
    assert abs(peak - f0) < 4.0
    # channels-first int16 input is scaled by 32768 and mixed to mono
    i16 = (stereo.T * 32767).astype(np.int16)
    np.testing.assert_allclose(load_waveform(i16, sr), y, atol=2e-4)


def test_waveform_input_errors():
    with pytest.raises(InputError):
        load_waveform(np.array([0.0, np.nan]), SR)
    with pytest.raises(InputError):
        load_waveform(np.zeros((2, 3, 4)), SR)
    with pytest.raises(InputError):
        load_waveform(np.full(100, 20000.0), SR)
    with pytest.raises(InputError):
        compute_features(np.zeros(1000), SR, AudioConfig(frontend="ds"))


def test_frontend_from_array_shapes():
    assert frontend_from_array("ds", np.zeros((5, 16, 29))).shape == (5, 16, 29)
    assert frontend_from_array("hu", np.zeros((5, 2, 1024))).shape == (5, 2, 1024)
    assert frontend_from_array("hu", np.zeros((10, 1024))).shape == (5, 2, 1024)
    assert frontend_from_array("wavlm", np.zeros((5, 768))).shape == (5, 1, 768)
    assert frontend_from_array("wavlm", np.zeros((5, 4, 768))).shape == (5, 4, 768)
    for kind, arr in [("ds", np.zeros((5, 29))), ("ds", np.zeros((5, 16, 30))), ("hu", np.zeros((5, 3, 1024))),
                      ("wavlm", np.zeros(5)), ("what", np.zeros((5, 2, 2))), ("ds", np.full((1, 16, 29), np.inf))]:
        with pytest.raises(InputError):
            frontend_from_array(kind, arr)


def test_smoother_on_an_impulse():
    torch.manual_seed(0)
    D, N, hit = 6, 20, 10
    sm = AudioSmoother(D, 8)
    seq = torch.zeros(N, D)
    seq[hit, 2] = 1.0
    with torch.no_grad():
        out = sm(frame_windows(seq, 8))
        w = sm.weights(frame_windows(seq, 8))
    # frame i sees frames i-4 .. i+3: the impulse reaches frames 7 .. 14 only
    for i in range(N):
        if 7 <= i <= 14:
            pos = hit - (i - 4)
            assert torch.allclose(out[i], w[i, pos] * seq[hit])
            assert 0 < float(out[i, 2]) < 1
        else:
            assert torch.count_nonzero(out[i]) == 0
    assert torch.allclose(w.sum(-1), torch.ones(N))
    # a constant sequence is a fixed point away from the zero-padded edges
    const = torch.ones(N, D) * torch.arange(D)
    with torch.no_grad():
        c_out = sm(frame_windows(const, 8))
    assert torch.allclose(c_out[4:-3], const[4:-3], atol=1e-6)


def test_frame_windows_zero_pad():
    seq = torch.arange(1, 6, dtype=torch.float32)[:, None]  # frames 1..5
    w = frame_windows(seq, 8)
    assert w.shape == (5, 8, 1)
    assert w[0, :, 0].tolist() == [0, 0, 0, 0, 1, 2, 3, 4]
    assert w[4, :, 0].tolist() == [1, 2, 3, 4, 5, 0, 0, 0]


def test_audio_net_shapes_and_index():
    torch.manual_seed(0)
    for C, W in [(80, 16), (29, 16), (1024, 2), (768, 1)]:
        net = AudioNet(C, W, AudioConfig(dim=32))
        x = torch.randn(12, W, C)
        full = net(x)
        assert full.shape == (12, 32)
        idx = torch.tensor([0, 5, 11])
        torch.testing.assert_close(net(x, idx), full[idx])
    with pytest.raises(InputError):
        AudioNet(80, 16)(torch.randn(3, 8, 80))
