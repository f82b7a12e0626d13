# SPDX-License-Identifier: GPL-3.0-or-later
"""Caustic Bake extension root.

Thin on purpose: Blender imports this package (as ``bl_ext.<repo>.caustic_bake``) and calls
:func:`register` / :func:`unregister`; everything lives in :mod:`.addon`.
"""

from .addon import register, unregister

__all__ = ["register", "unregister"]
