"""What every layer may use to run: the drjit/mitsuba door (``backend``) and Ctrl-C handling
(``interrupts``).

May import: the standard library, ``autoalign.errors``. Nothing else of autoalign.
"""
