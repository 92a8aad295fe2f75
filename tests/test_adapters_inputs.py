"""The Gymnasium / PettingZoo adapters refuse a bad world count with one ConfigError naming it
(cfrace.rl.inputs.check_inputs, as `cfrace train --envs`), not a torch error from deep inside."""

from __future__ import annotations

import numpy as np
import pytest

from cfrace.errors import ConfigError

pytest.importorskip("gymnasium")


@pytest.mark.parametrize("num_envs", [2.5, 0, True, "4"])
def test_a_bad_num_envs_is_one_config_error(num_envs):
    from cfrace.rl.adapters.gymnasium_env import RaceVectorEnv

    with pytest.raises(ConfigError, match=r"num_envs\) must be a whole number of at least 1, got "):
        RaceVectorEnv(num_envs, "ds")


def test_a_numpy_integer_is_a_world_count():
    from cfrace.rl.adapters.gymnasium_env import RaceVectorEnv

    assert RaceVectorEnv(np.int64(2), "ds").num_envs == 2
