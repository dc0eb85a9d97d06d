"""PortAudio devices through sounddevice: listing, and checking a configuration before a stream is opened."""
from __future__ import annotations

from sonicverse_core.errors import DeviceError, require


def _sd():
    return require("sounddevice", "real-time audio")


def list_devices() -> list[dict]:
    sd = _sd()
    apis = sd.query_hostapis()
    out = []
    for i, d in enumerate(sd.query_devices()):
        out.append({"index": i, "name": d["name"], "hostapi": apis[d["hostapi"]]["name"],
                    "inputs": d["max_input_channels"], "outputs": d["max_output_channels"],
                    "default_sample_rate": d["default_samplerate"],
                    "default_low_latency_ms": round(1000 * d["default_low_output_latency"], 2)})
    return out


def _describe(devs: list[dict]) -> str:
    if not devs:
        return "no audio devices at all (no sound card and no JACK server running?)"
    return "; ".join(f"[{d['index']}] {d['name']} ({d['hostapi']}, {d['inputs']} in / {d['outputs']} out)"
                     for d in devs)


def resolve(device, kind: str) -> dict:
    """The device dict for a name (case-insensitive substring), an index, or None (the default)."""
    sd = _sd()
    devs = list_devices()
    try:
        info = sd.query_devices(device, kind)
    except (ValueError, sd.PortAudioError) as exc:
        what = "default " + kind + " device" if device is None else f"{kind} device '{device}'"
        raise DeviceError(f"no {what} ({str(exc).splitlines()[0]}); available: {_describe(devs)}; "
                          f"list them with 'sonicverse audio devices'") from None
    return next(d for d in devs if d["name"] == info["name"] and d["index"] == info["index"])


def check(cfg) -> tuple[dict, dict | None]:
    """Validate the output (stereo) and input (microphone) devices for ``cfg``; (output, input or None)."""
    sd = _sd()
    out = resolve(cfg.device, "output")
    if out["outputs"] < 2:
        raise DeviceError(f"output device '{out['name']}' has {out['outputs']} output channel; binaural audio "
                          f"needs 2 (choose headphones or a stereo device with --device)")
    inp = None
    if cfg.mic:
        inp = resolve(cfg.input_device if cfg.input_device is not None else cfg.device, "input")
        if inp["inputs"] <= cfg.mic_channel:
            raise DeviceError(f"input device '{inp['name']}' has {inp['inputs']} input channels; the microphone "
                              f"channel {cfg.mic_channel} does not exist")
    for d, fn, ch in ((out, sd.check_output_settings, 2), (inp, sd.check_input_settings, cfg.mic_channel + 1)):
        if d is None:
            continue
        try:
            fn(device=d["index"], samplerate=cfg.sample_rate, channels=ch, dtype="float32")
        except sd.PortAudioError as exc:
            msg = str(exc).splitlines()[0]
            if "sample rate" in msg.lower():
                raise DeviceError(f"device '{d['name']}' does not support {cfg.sample_rate} Hz (it runs at "
                                  f"{d['default_sample_rate']:.0f} Hz); use --sample-rate "
                                  f"{d['default_sample_rate']:.0f}") from None
            raise DeviceError(f"device '{d['name']}' refuses {cfg.sample_rate} Hz / {ch} channels: {msg}") from None
    return out, inp
