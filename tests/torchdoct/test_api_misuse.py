"""Python API misuse (issue class 11): a wrong type or a meaningless value is a ``TypeError`` or
``ValueError`` naming the argument and the fix, never an internal message, an ``AttributeError`` or a
silent truncation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdoct as td


@pytest.mark.parametrize("call", [td.simulate, td.make_plan])
def test_a_scene_name_instead_of_a_scene_says_to_load_it(call):
    with pytest.raises(TypeError, match=r"td\.load_scene\('example'\)"):
        call("example")
    with pytest.raises(TypeError, match="takes a Scene"):
        call(42)


def test_a_phantom_name_instead_of_a_phantom_says_to_load_it():
    with pytest.raises(TypeError, match=r"td\.load_phantom\('spheroid'\)"):
        td.render("spheroid")


@pytest.mark.parametrize(
    "kw,value",
    [
        ("trials", 2.5),
        ("trials", True),
        ("trials", 64.0),
        ("seed", 1.5),
        ("seed", False),
        ("trials", "64"),
        ("chunk_trials", 64.5),
    ],
)
def test_non_integer_counts_and_seeds_are_refused_not_truncated(small_scene, kw, value):
    with pytest.raises(TypeError, match=f"{kw} must be an integer"):
        td.simulate(small_scene, **{kw: value})


def test_numpy_integers_are_integers(small_scene):
    a = td.simulate(small_scene, trials=np.int64(64), seed=np.int32(3))
    b = td.simulate(small_scene, trials=64, seed=3)
    assert torch.equal(a.signals, b.signals)


def test_liv_of_a_complex_field_asks_for_intensity():
    field = torch.randn(4, 8, dtype=torch.complex64, generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match=r"liv\(intensity\).*complex.*abs\(\) \*\* 2"):
        td.liv(field)
    v = td.liv(field.abs() ** 2)
    assert not v.is_complex() and torch.allclose(v, td.liv(field.real**2 + field.imag**2), rtol=1e-4)


@pytest.mark.parametrize("value,error", [(3.0, TypeError), (torch.tensor(3.0), ValueError), ([1.0, 2.0], TypeError)])
def test_liv_of_a_number_names_the_argument(value, error):
    with pytest.raises(error, match=r"liv\(intensity\)"):
        td.liv(value)


def test_ocds_of_too_few_frames_or_bad_times_names_the_argument():
    with pytest.raises(ValueError, match=r"ocds\(intensity\): 1 frame"):
        td.ocds(torch.ones(1), [0.0])
    x = torch.rand(4, 5, generator=torch.Generator().manual_seed(0)) + 0.5
    with pytest.raises(ValueError, match=r"ocds\(frame_times_s\).*increase strictly.*frame_times_s\[2\]"):
        td.ocds(x, [0.0, 0.2, 0.2, 0.4, 0.6])
    with pytest.raises(ValueError, match=r"ocds\(frame_times_s\).*increase strictly.*frame_times_s\[1\]"):
        td.ocds(x, [0.4, 0.2, 0.6, 0.8, 1.0])
    with pytest.raises(ValueError, match=r"ocds\(frame_times_s\): 4 frame times for 5 frames"):
        td.ocds(x, [0.0, 0.2, 0.4, 0.6])
    with pytest.raises(ValueError, match=r"ocds\(frame_times_s\): frame_times_s\[1\] = nan"):
        td.ocds(x, [0.0, float("nan"), 0.4, 0.6, 0.8])
    with pytest.raises(TypeError, match=r"ocds\(intensity\).*complex"):
        td.ocds(torch.ones(4, 5, dtype=torch.complex64), [0.0, 0.2, 0.4, 0.6, 0.8])


def test_ocds_refuses_times_and_delay_ranges_that_are_not_numbers_naming_the_argument():
    x = torch.rand(4, 8, generator=torch.Generator().manual_seed(0)) + 0.5
    times = [0.2 * i for i in range(8)]
    with pytest.raises(TypeError, match=r"ocds\(frame_times_s\).*str '0\.0'"):
        td.ocds(x, [str(t) for t in times], delay_range_s=(0.2, 0.6))
    for bad in [(float("nan"), 0.6), (0.6, 0.2), (0.2, float("inf"))]:
        with pytest.raises(ValueError, match=r"ocds\(delay_range_s\): delay_range_s must be finite"):
            td.ocds(x, times, delay_range_s=bad)
    with pytest.raises(TypeError, match=r"ocds\(delay_range_s\)"):
        td.ocds(x, times, delay_range_s=("0.2", "0.6"))
    with pytest.raises(ValueError, match=r"ocds\(delay_range_s\).*fewer than 2 delays") as info:
        td.ocds(x, times, delay_range_s=(0.01, 0.1))
    assert "--" not in str(info.value)  # the API names its argument, not a command-line option


def test_liv_of_one_frame_or_a_mask_is_refused():
    with pytest.raises(ValueError, match=r"liv\(intensity\): 1 frame"):
        td.liv(torch.ones(5, 1))
    with pytest.raises(TypeError, match=r"liv\(intensity\).*bool"):
        td.liv(torch.ones(5, 8, dtype=torch.bool))


@pytest.mark.parametrize("call,what", [(td.load_scene, "td.load_scene"), (td.load_phantom, "td.load_phantom")])
@pytest.mark.parametrize("value", [42, None, ""])
def test_a_loader_given_no_path_says_what_it_takes(call, what, value):
    with pytest.raises(TypeError, match=rf"{what}\(path\) takes the path of a .* file or the name of a shipped"):
        call(value)


def test_a_wrong_device_tolerance_or_system_list_is_named(small_scene):
    with pytest.raises(ValueError, match="device 'gpu' is not a torch device name"):
        td.simulate(small_scene, trials=4, device="gpu")
    with pytest.raises(TypeError, match="truncation tolerance must be a number in"):
        td.simulate(small_scene, trials=4, truncation_tolerance="1e-3")
    with pytest.raises(TypeError, match="systems must be a system name or a list"):
        td.render(td.load_phantom("spheroid"), systems=3)


def test_ocds_takes_frame_times_in_order_from_any_sequence_but_not_from_a_mapping():
    x = torch.rand(4, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64) + 0.5
    times = [0.2 * i for i in range(8)]
    want = td.ocds(x, times, delay_range_s=(0.2, 0.6))
    for given in (tuple(times), (t for t in times), np.asarray(times), torch.tensor(times, dtype=torch.float64)):
        torch.testing.assert_close(td.ocds(x, given, delay_range_s=(0.2, 0.6)), want, rtol=0, atol=0)
    with pytest.raises(TypeError, match=r"ocds\(frame_times_s\).*got dict"):
        td.ocds(x, dict(enumerate(times)), delay_range_s=(0.2, 0.6))
