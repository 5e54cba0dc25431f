"""Self-supervised adaptation of the light network to a user's own unlabelled captures (``mode=adapt``).

:mod:`.frames` reads and prepares the frames, :mod:`.guards` says what is refused,
:mod:`selfsup.teacher` turns the per-frame search's lights into targets, :mod:`.loop` runs the fine-tuning (docs/training.md, "Adapting to your captures").
"""

from selfsup.adapt.frames import AdaptFrames, FrameBatch, FrameOptions, UserFrame, collate_frames, load_frames, teach
from selfsup.adapt.guards import GuardOptions, degenerate_lights, guard_penalty, refusals, surface_violation
from selfsup.adapt.loop import AdaptOptions, Procedural, adapt_files
from selfsup.losses import TeacherOptions, teacher_loss

__all__ = ["AdaptOptions", "Procedural", "adapt_files", "FrameOptions", "UserFrame", "FrameBatch", "AdaptFrames",
           "load_frames", "collate_frames", "GuardOptions", "surface_violation", "degenerate_lights", "guard_penalty",
           "refusals", "TeacherOptions", "teacher_loss", "teach"]
