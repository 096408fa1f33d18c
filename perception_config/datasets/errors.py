"""The errors and warnings of the dataset readers (BOP files, their images)."""


class BopFormatError(ValueError):
    """A BOP file that is missing required content or holds impossible values."""


class BopAnnotationWarning(UserWarning):
    """A BOP file whose values were repaired on reading (rotations projected onto SO(3))."""
