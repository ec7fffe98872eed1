"""The GalSim config plug-in ``bfpsf.galsim``: sensor type ``BrighterFatter`` run by the
``galsim`` executable, against ``type: Silicon`` on the same scene.

The scene is examples/galsim_config/scene.yaml (stars of 3e4 to 2e6 e-, photon-shot on
stamps). Sizes are compared as growths: each BF image minus its BF-free twin drawn with the
same random numbers (no sensor for BrighterFatter; SiliconSensor with strength 1e-9 for
Silicon), which removes the photon noise common to both and leaves the BF change of each
star. The BrighterFatter scene's stars are the Moffat convolved with SiliconSensor's charge
diffusion (`silicon_diffusion_sigma`): BF acts on the charge as it lands, diffusion included.
"""

import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

galsim = pytest.importorskip("galsim")

import bfpsf.galsim  # noqa: E402,F401  (registers the sensor type)
from bfpsf import adaptive_moments  # noqa: E402
from bfpsf.errors import BFPSFInputError  # noqa: E402
from bfpsf.interop.silicon_truth import silicon_diffusion_sigma  # noqa: E402
from bfpsf.measure.slopes import fit_bf_slope  # noqa: E402
from bfpsf.model.redistribution import redistribute  # noqa: E402

SCENE = Path(__file__).resolve().parents[1] / "examples" / "galsim_config" / "scene.yaml"
SENSOR = "lsst_e2v_50_8"  # the sensor of the e2v_flats_calibration fixture
STAMP = 32


def _scene(tmp_path, calibration, tiles, name, sensor, diffusion):
    """The example scene with ``tiles`` x ``tiles`` stars and the given sensor."""
    config = yaml.safe_load(SCENE.read_text())
    count = tiles * tiles
    config["gal"]["flux"] = (f"$np.exp(np.log(3e4) + (np.log(2e6) - np.log(3e4)) * "
                             f"(obj_num % {count}) / {count - 1}.)")
    if diffusion:
        moffat = {key: config["gal"][key] for key in ("type", "beta", "fwhm")}
        config["gal"] = {"type": "Convolve", "flux": config["gal"]["flux"],
                         "items": [moffat, {"type": "Gaussian", "sigma": float(diffusion)}]}
    config["image"].update(nx_tiles=tiles, ny_tiles=tiles)
    if sensor is None:
        del config["image"]["sensor"]
    elif sensor == "bf":
        config["image"]["sensor"]["calib"] = str(calibration)
    else:
        config["image"]["sensor"] = sensor
    config["output"]["file_name"] = str(tmp_path / f"{name}.fits")
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


#: the ``galsim`` executable of this Python's environment (found beside the interpreter when the
#: suite runs as ``venv/bin/python -m pytest`` without the environment activated)
GALSIM = shutil.which("galsim", path=str(Path(sys.executable).parent)) or "galsim"


def _run_galsim(config_path):
    """Run the ``galsim`` executable; return its CPU time, s (the machine may be shared)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([GALSIM, str(config_path), "-v", "0"], check=True, cwd=config_path.parent)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)


def _sizes(path, tiles):
    """sigma = sqrt((Mxx + Myy) / 2) of each stamp, pixels, in obj_num order (row by row)."""
    from astropy.io import fits

    image = fits.getdata(path)
    sizes = []
    for index in range(tiles * tiles):
        row, column = divmod(index, tiles)
        moments = adaptive_moments(image[row * STAMP:(row + 1) * STAMP,
                                         column * STAMP:(column + 1) * STAMP])
        sizes.append(np.sqrt(0.5 * (moments.mxx + moments.myy)))
    return np.array(sizes)


def _fluxes(tiles):
    count = tiles * tiles
    return np.exp(np.log(3e4) + (np.log(2e6) - np.log(3e4)) * np.arange(count) / (count - 1))


def _predicted_growth(shifts, diffusion, fluxes):
    """Slope of sigma against flux (per 100 ke-) of the noiseless star redistributed."""
    profile = galsim.Convolve(galsim.Moffat(beta=3.5, fwhm=3.5), galsim.Gaussian(sigma=diffusion))
    unit = profile.drawImage(nx=STAMP, ny=STAMP, scale=1.0).array
    sizes = []
    for flux in (fluxes.min(), fluxes.max()):
        moments = adaptive_moments(redistribute(flux * unit, shifts))
        sizes.append(np.sqrt(0.5 * (moments.mxx + moments.myy)))
    return (sizes[1] - sizes[0]) / ((fluxes.max() - fluxes.min()) / 1e5)


def _compare_with_silicon(tmp_path, calibration, tiles):
    path = tmp_path / "calib.fits"
    calibration.write(path)
    diffusion = silicon_diffusion_sigma(SENSOR)
    runs = {"bf": ("bf", diffusion), "bf_twin": (None, diffusion),
            "silicon": ({"type": "Silicon", "name": SENSOR}, 0.0),
            "silicon_twin": ({"type": "Silicon", "name": SENSOR, "strength": 1e-9}, 0.0)}
    times, sizes = {}, {}
    for name, (sensor, blur) in runs.items():
        config = _scene(tmp_path, path, tiles, name, sensor, blur)
        times[name] = _run_galsim(config)
        sizes[name] = _sizes(tmp_path / f"{name}.fits", tiles)
    fluxes = _fluxes(tiles)
    growth = {kind: fit_bf_slope(fluxes, sizes[kind] - sizes[f"{kind}_twin"])
              for kind in ("bf", "silicon")}
    # the calibration's carried error: the growth predicted with each of its shift samples
    samples = [_predicted_growth(shifts, diffusion, fluxes)
               for shifts in calibration.shift_samples()]
    nominal = _predicted_growth(calibration.shifts, diffusion, fluxes)
    carried = float(np.std(samples, ddof=1)) / nominal  # relative
    # the sensors' own cost: each run minus the sensor-less run of the same scene (bf_twin;
    # the Silicon twin is a SiliconSensor too and costs as much as Silicon)
    speedup = (times["silicon"] - times["bf_twin"]) / max(times["bf"] - times["bf_twin"], 0.01)
    print(f"\nsize growth, pix per 100 ke-: BrighterFatter {growth['bf'].slope:.5f} +- "
          f"{growth['bf'].slope_err:.5f}, Silicon {growth['silicon'].slope:.5f} +- "
          f"{growth['silicon'].slope_err:.5f}; calibration's carried error {100 * carried:.1f} %"
          f"\nCPU time: BrighterFatter {times['bf']:.1f} s, Silicon {times['silicon']:.1f} s "
          f"(x{times['silicon'] / times['bf']:.1f}); sensor alone (minus the BF-free twin) "
          f"x{speedup:.0f}")
    return growth, carried, times


def _assert_equal_growth(growth, carried):
    bf, silicon = growth["bf"], growth["silicon"]
    assert silicon.slope > 5 * silicon.slope_err  # the growth is measured
    # equal within the calibration's carried error and the two measurements' errors (2 sigma)
    tolerance = 2 * np.sqrt(bf.slope_err**2 + silicon.slope_err**2
                            + (carried * silicon.slope) ** 2)
    assert abs(bf.slope - silicon.slope) < tolerance, (bf, silicon, carried)


def test_galsim_executable_bf_sensor_matches_silicon_quick(tmp_path, e2v_flats_calibration):
    # physics only: the times are printed, and the speed is measured side by side in
    # benchmarks/bench_redistribution.py (a fresh clone's first run compiles numba's kernels
    # inside the BrighterFatter time: 7.2 s against Silicon's 4.7 s, where a warm cache
    # gives the other order)
    growth, carried, _ = _compare_with_silicon(tmp_path, e2v_flats_calibration, tiles=5)
    _assert_equal_growth(growth, carried)


@pytest.mark.slow
def test_galsim_executable_bf_sensor_matches_silicon(tmp_path, e2v_flats_calibration):
    growth, carried, times = _compare_with_silicon(tmp_path, e2v_flats_calibration, tiles=12)
    _assert_equal_growth(growth, carried)


def test_fft_drawn_objects_get_the_redistribution_of_their_drawn_image(tmp_path,
                                                                      e2v_flats_calibration):
    path = tmp_path / "calib.fits"
    e2v_flats_calibration.write(path)
    config = {"modules": ["bfpsf.galsim"],
              "gal": {"type": "Moffat", "beta": 3.5, "fwhm": 3.5, "flux": 1.5e6},
              "stamp": {"draw_method": "auto", "dtype": "float64"},
              "image": {"type": "Single", "size": 32, "pixel_scale": 1.0, "random_seed": 5,
                        "sensor": {"type": "BrighterFatter", "calib": str(path)}}}
    drawn = galsim.config.BuildImage(galsim.config.CopyConfig(config))
    # the same path through GalSim's neutral sensor: the drawn image landed without BF
    config["image"]["sensor"] = {"type": "Simple"}
    plain = galsim.config.BuildImage(config)
    expected = redistribute(plain.array.astype(float), e2v_flats_calibration.shifts)
    # float64 stamps; GalSim's photons from the image carry float32 rounding (differences of
    # 8e-8 of a pixel seen), far below the BF change (1e-3 of the peak, asserted below)
    np.testing.assert_allclose(drawn.array, expected, rtol=0, atol=1e-6 * plain.array.max())
    assert np.abs(expected - plain.array).max() > 1e-3 * plain.array.max()  # BF is there


def test_sensor_keys_and_errors(tmp_path, e2v_flats_calibration):
    from bfpsf import BFSensor

    path = tmp_path / "calib.fits"
    e2v_flats_calibration.write(path)
    base = {"modules": ["bfpsf.galsim"], "image": {"sensor": {
        "type": "BrighterFatter", "calib": str(path), "gain": 2.0, "nsteps": 3}}}
    galsim.config.ImportModules(base)
    sensor = galsim.config.BuildSensor(base["image"], "sensor", base)
    assert sensor == BFSensor(e2v_flats_calibration.shifts, gain=2.0, nsteps=3)
    base["image"]["sensor"] = {"type": "BrighterFatter", "calib": str(tmp_path / "no.fits")}
    with pytest.raises(BFPSFInputError, match="no.fits does not exist"):
        galsim.config.BuildSensor(base["image"], "sensor", base)
    # through the executable: a one-line GalSim error naming the file, not a sensor-less image
    config = _scene(tmp_path, tmp_path / "no.fits", 2, "missing", "bf", 0.0)
    run = subprocess.run([GALSIM, str(config)], capture_output=True, text=True,
                         cwd=tmp_path)
    assert run.returncode != 0 and "no.fits does not exist" in run.stderr
