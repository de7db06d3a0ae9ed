"""A deconvolver factory that fails on a poisoned frame, importable by a spawned solver child (a
module-level name: the child unpickles it by reference)."""

from thermod.physics.deconv import Deconvolver

POISON = 1234.0       # a frame of this constant value makes the solve raise


class CrashingDeconvolver(Deconvolver):
    def run(self, image, kernel, **kw):
        if abs(float(image.mean()) - POISON) < 1e-3:
            raise FloatingPointError("injected worker fault")
        return super().run(image, kernel, **kw)


def crashing_factory(deblur):
    return CrashingDeconvolver(deblur.method, deblur.alpha, deblur.lam)


class HangingDeconvolver(Deconvolver):
    def run(self, image, kernel, **kw):
        if abs(float(image.mean()) - POISON) < 1e-3:
            import time
            time.sleep(60.0)          # a hung solve (a deadlock in a library, a stuck page-in)
        return super().run(image, kernel, **kw)


def hanging_factory(deblur):
    return HangingDeconvolver(deblur.method, deblur.alpha, deblur.lam)
