"""Benchmark of the charge-redistribution engine (issue 3).

1. Forward redistribution (G15 eq. scrambling_model) of a 4k x 4k image: bfpsf (blocked
   overlap-save FFT shared by the N and E kernels, double and single precision) against a
   plain implementation with two `scipy.signal.fftconvolve` calls, timed in the same run.
2. One bright star (2.7e6 e-, Moffat FWHM 4 px) drawn with photon shooting through
   `bfpsf.interop.galsim.BFSensor` and through `galsim.SiliconSensor`: whole drawImage, and
   the sensor's accumulate alone on the same photons.

Single core: run as ``OMP_NUM_THREADS=1 python benchmarks/bench_redistribution.py``
(the script sets it if unset). Prints timings (best of --repeat) and ratios.
"""

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.signal  # noqa: E402

from bfpsf.model.redistribution import redistribute  # noqa: E402
from bfpsf.shifts import BoundaryShifts  # noqa: E402


def plain_fftconvolve_redistribute(image, shifts):
    """Reference: each boundary-shift field by scipy.signal.fftconvolve, then the fluxes."""
    shift_north = scipy.signal.fftconvolve(image, shifts.north[::-1, ::-1], mode="same")
    shift_east = scipy.signal.fftconvolve(image, shifts.east[::-1, ::-1], mode="same")
    flux_north = 0.25 * shift_north[:-1, :] * (image[:-1, :] + image[1:, :])
    flux_east = 0.25 * shift_east[:, :-1] * (image[:, :-1] + image[:, 1:])
    result = image.copy()
    result[:-1, :] += flux_north
    result[1:, :] -= flux_north
    result[:, :-1] += flux_east
    result[:, 1:] -= flux_east
    return result


def best_time(function, repeat):
    """Best wall-clock time of ``repeat`` runs (and the result of the last run)."""
    best, result = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def best_cpu_time(function, repeat):
    """Best process CPU time of ``repeat`` runs: on a shared, loaded machine this is closer to
    the single-core cost than the wall clock (page faults count as system CPU time)."""
    best = np.inf
    for _ in range(repeat):
        start = time.process_time()
        function()
        best = min(best, time.process_time() - start)
    return best


def bench_forward(size, repeat):
    shifts = BoundaryShifts.from_radial_profile(lambda r: 8e-7 * np.exp(-r / 1.2), 4)
    rng = np.random.default_rng(0)
    image = rng.poisson(5e3, (size, size)).astype(float)
    print(f"forward redistribution, {size} x {size}, radius {shifts.radius}, best of {repeat}"
          " (x: speed-up over plain fftconvolve)")
    runs = {"plain fftconvolve": lambda: plain_fftconvolve_redistribute(image, shifts),
            "bfpsf float64": lambda: redistribute(image, shifts),
            "bfpsf float32": lambda: redistribute(image, shifts, dtype=np.float32)}
    wall, cpu, results = {}, {}, {}
    for label, run in runs.items():
        wall[label], results[label] = best_time(run, repeat)
        cpu[label] = best_cpu_time(run, repeat)
    reference = results["plain fftconvolve"]
    delta = np.abs(reference - image).max()
    plain = "plain fftconvolve"
    for label in runs:
        line = (f"  {label:18s} wall {wall[label]:7.3f} s (x{wall[plain] / wall[label]:5.2f})"
                f"   cpu {cpu[label]:7.3f} s (x{cpu[plain] / cpu[label]:5.2f})")
        if label != plain:
            line += (f"   max|diff| / max|dQ| = "
                     f"{np.abs(results[label] - reference).max() / delta:.1e}")
        print(line)
    double, single = results["bfpsf float64"], results["bfpsf float32"]
    print(f"  charge conservation (float64, float32): "
          f"{abs(double.sum() - image.sum()) / image.sum():.1e}, "
          f"{abs(single.sum() - image.sum()) / image.sum():.1e} relative")


def bench_star(flux, repeat, name):
    import galsim

    from bfpsf.interop.galsim import BFSensor, silicon_boundary_shifts

    start = time.perf_counter()
    shifts = silicon_boundary_shifts(name)
    print(f"\nbright star {flux:.3g} e-, Moffat FWHM 4 px, {name} "
          f"(shifts read out in {time.perf_counter() - start:.1f} s, once)")
    profile = galsim.Moffat(beta=2.5, fwhm=4.0).withFlux(flux)
    sensors = {"BFSensor": BFSensor(shifts), "SiliconSensor": galsim.SiliconSensor(name),
               "no sensor": None}
    draws = {}
    for label, sensor in sensors.items():
        draws[label], _ = best_time(lambda: profile.drawImage(
            nx=61, ny=61, scale=1.0, method="phot", sensor=sensor,
            rng=galsim.BaseDeviate(1)), repeat)
    # method='auto' with a sensor: GalSim draws the profile on a 3x subsampled grid and turns
    # each sub-pixel into one weighted photon (no photon shooting).
    draws_auto = {}
    for label in ("BFSensor", "SiliconSensor"):
        sensor = sensors[label]
        draws_auto[label], _ = best_time(lambda: profile.drawImage(
            nx=61, ny=61, scale=1.0, method="auto", sensor=sensor), repeat)
    shot = profile.shoot(int(flux), galsim.BaseDeviate(2))
    shot.x += 30.0
    shot.y += 30.0
    accumulate, accumulate_cpu = {}, {}
    for label in ("BFSensor", "SiliconSensor"):
        sensor = sensors[label]

        def run():
            return sensor.accumulate(shot, galsim.ImageD(61, 61, xmin=0, ymin=0))

        accumulate[label], _ = best_time(run, repeat)
        accumulate_cpu[label] = best_cpu_time(run, repeat)
    print(f"  drawImage   no sensor {draws['no sensor']:.3f} s, "
          f"BFSensor {draws['BFSensor']:.3f} s, SiliconSensor {draws['SiliconSensor']:.3f} s: "
          f"BFSensor x{draws['SiliconSensor'] / draws['BFSensor']:.1f} faster")
    print(f"  accumulate  BFSensor {accumulate['BFSensor']:.4f} s, SiliconSensor "
          f"{accumulate['SiliconSensor']:.3f} s: BFSensor "
          f"x{accumulate['SiliconSensor'] / accumulate['BFSensor']:.0f} faster "
          "(sensor work alone, same photons)")
    print(f"  drawImage(method='auto', weighted photons from a 3x subsampled image): BFSensor "
          f"{draws_auto['BFSensor']:.3f} s, SiliconSensor {draws_auto['SiliconSensor']:.3f} s; "
          f"BFSensor x{draws['SiliconSensor'] / draws_auto['BFSensor']:.0f} faster than "
          "SiliconSensor with photon shooting")
    print(f"  accumulate  cpu: BFSensor {accumulate_cpu['BFSensor']:.4f} s, SiliconSensor "
          f"{accumulate_cpu['SiliconSensor']:.3f} s: "
          f"x{accumulate_cpu['SiliconSensor'] / accumulate_cpu['BFSensor']:.0f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=4096, help="image side (default 4096)")
    parser.add_argument("--repeat", type=int, default=3, help="timings: best of N (default 3)")
    parser.add_argument("--flux", type=float, default=2.7e6, help="star flux, e- (2.7e6)")
    parser.add_argument("--sensor", default="lsst_itl_50_8", help="GalSim sensor name")
    parser.add_argument("--skip-star", action="store_true", help="only the forward benchmark")
    args = parser.parse_args()
    print(f"OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}, scipy.fft workers=1")
    bench_forward(args.size, args.repeat)
    if not args.skip_star:
        bench_star(args.flux, args.repeat, args.sensor)


if __name__ == "__main__":
    main()
