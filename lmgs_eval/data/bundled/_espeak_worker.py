"""Run as a script: speak one utterance with espeak-ng (ctypes) in a fresh process.

espeak-ng keeps internal state between utterances (noise, intonation) that even
``espeak_Terminate`` does not reset, so the same text gives different samples depending on
what was spoken before in the process. A fresh process per utterance makes the output a
function of (text, voice) only. Input: one JSON line ``{"text", "voice"}`` on stdin. Output:
one JSON line (sample rate, phoneme events or an error) then the raw int16 samples.
"""

import ctypes
import json
import sys


class _Event(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),
        ("sample", ctypes.c_int),
        ("user_data", ctypes.c_void_p),
        ("id", ctypes.c_char * 8),
    ]


def main() -> int:
    import espeakng_loader

    req = json.loads(sys.stdin.readline())
    lib = ctypes.CDLL(espeakng_loader.get_library_path())
    lib.espeak_Initialize.restype = ctypes.c_int
    # synchronous output, default buffer, data path, phoneme events with IPA names
    sr = lib.espeak_Initialize(2, 0, espeakng_loader.get_data_path().encode(), 0x1 | 0x2)
    out = sys.stdout.buffer
    if sr <= 0:
        out.write((json.dumps({"error": "espeak-ng initialisation failed"}) + "\n").encode())
        return 1
    chunks, events = [], []
    cb_type = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))

    def collect(wav, n, ev):
        if n > 0:
            chunks.append(ctypes.string_at(wav, 2 * n))
        i = 0
        while ev[i].type != 0:
            if ev[i].type == 7:  # phoneme event
                events.append([int(ev[i].audio_position), ev[i].id.decode("utf-8", "replace")])
            i += 1
        return 0

    cb = cb_type(collect)
    lib.espeak_SetSynthCallback(cb)
    if lib.espeak_SetVoiceByName(req["voice"].encode()) != 0:
        out.write((json.dumps({"error": f"voice espeak:{req['voice']}: not known to espeak-ng"}) + "\n").encode())
        return 1
    raw = req["text"].encode("utf-8")
    lib.espeak_Synth(raw, len(raw) + 1, 0, 1, 0, 1 | 0x1000, None, None)  # UTF-8, pause at the end
    out.write((json.dumps({"sr": sr, "events": events}) + "\n").encode())
    out.write(b"".join(chunks))
    out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
