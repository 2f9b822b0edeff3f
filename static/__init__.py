"""What vservo ships besides code: the default cell file, the demo job, the study snapshot, screenshots."""

if __name__ != "vservo.static":  # one import name: a second copy would split every class in two
    raise ImportError(f"vservo's static is imported as vservo.static, not as {__name__!r}")
