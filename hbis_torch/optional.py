"""Optional dependencies, imported where they are used, each with one clear error saying how to
install it (the package's extras)."""

from __future__ import annotations

from hbis_torch.errors import HbisInputError


def import_cv2(what: str):
    """OpenCV, or one clear HbisInputError saying how to install it (the optional extra)."""
    try:
        import cv2
    except ImportError:
        raise HbisInputError(f"{what} needs OpenCV: pip install 'hbis-torch[camera]' "
                             "(or opencv-python-headless)") from None
    return cv2
