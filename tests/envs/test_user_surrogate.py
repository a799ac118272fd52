"""A surrogate reward of the user's own is checked where it is given: from shapes (its signature, one
float per state) and, in the reward diagnosis, at sampled states (a NaN or flat gradient); every
refusal is one line naming the function, from Python an ``EnvError``, from the command line exit 2."""
import pytest
from conftest import refused_in_one_line
from envs_for_tests import (Cart, constant_reward, nan_reward, raising_reward, reward_of_state_and_action,
                            string_reward, vector_reward)

from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError

# What each malformed surrogate makes the check say after its name.
MALFORMED = [
    (reward_of_state_and_action, "reward_of_state_and_action takes (state, action): it is called with one argument, "
                                 "the state a step reaches"),
    (vector_reward, "vector_reward returns an array of shape (2,) for one state: it must return one number per state"),
    (raising_reward, "raising_reward fails on the state a step reaches: ValueError: no target in this state"),
    (string_reward, "string_reward returns str ('near'), not a number"),
]


@pytest.mark.parametrize("reward, words", MALFORMED, ids=[reward.__name__ for reward, _ in MALFORMED])
def test_a_surrogate_of_the_wrong_shape_is_refused_in_the_librarys_terms_naming_it(reward, words):
    with pytest.raises(EnvError) as refusal:
        env_task(Cart("step"), horizon=5, surrogate_reward=reward, diagnose=False)
    message = str(refusal.value)
    assert message.startswith(f"Cart: the surrogate reward envs_for_tests:{words}"), message
    assert "\n" not in message


def test_a_nan_or_flat_surrogate_is_refused_as_the_users_function_not_the_envs_reward():
    with pytest.raises(EnvError) as nan:
        env_task(Cart("smooth"), horizon=5, surrogate_reward=nan_reward)
    assert str(nan.value).startswith("Cart: the surrogate reward envs_for_tests:nan_reward's gradient is NaN at 100% "
                                     "of sampled states"), nan.value
    assert "fix envs_for_tests:nan_reward" in str(nan.value) and "reward of your own" not in str(nan.value)
    # Flat: refused (never smoothed), with advice for the surrogate, not for the env's reward.
    with pytest.raises(EnvError) as flat:
        env_task(Cart("smooth"), horizon=5, surrogate_reward=constant_reward)
    assert str(flat.value).startswith("Cart: the surrogate reward envs_for_tests:constant_reward's gradient is zero at "
                                      "every sampled state and action"), flat.value
    assert "give envs_for_tests:constant_reward a slope" in str(flat.value)
    assert "reward of your own" not in str(flat.value)


def test_the_command_line_refuses_a_bad_surrogate_in_one_line_with_exit_2(tmp_path, capsys):
    for reward, words in MALFORMED + [(nan_reward, "nan_reward's gradient is NaN at 100% of sampled states")]:
        refused_in_one_line(capsys, tmp_path / "no", f"the surrogate reward envs_for_tests:{words}", "--env",
                            "envs_for_tests:make_cart", "--surrogate-reward", f"envs_for_tests:{reward.__name__}",
                            "--steps", "5", "--epochs", "1", "--no-progress")
