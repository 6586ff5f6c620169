"""Evaluation: the paper's protocol, image-quality and geometry metrics, peer baselines.

:mod:`.cases` (cases with ground truth and their datasets), :mod:`.registration` (a canvas
on the GT grid), :mod:`.scoring`, :mod:`.geometry` (Sampson and pose errors against GT
cameras), :mod:`.metrics`, :mod:`.baselines` (the methods), :mod:`.runner` and
:mod:`.report` (the ``pis3r eval`` command).
"""
