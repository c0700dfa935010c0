"""The evaluation's second process (mixed_traffic.evaluation.background): its answer, its failures, its fallback."""

import os
import signal

import pytest

from mixed_traffic.evaluation.background import Background, can_fork


def test_the_child_answers_what_the_call_returns_and_runs_in_another_process():
    job = Background(lambda: (os.getpid(), sum(range(100))))
    assert job.forked == can_fork() and can_fork()  # Linux, no CUDA here
    pid, total = job.result()
    assert total == 4950 and pid != os.getpid()


def test_without_fork_the_call_runs_here_with_the_same_answer():
    job = Background(lambda: (os.getpid(), sum(range(100))), enabled=False)
    assert not job.forked and job.result() == (os.getpid(), 4950)


def test_a_failure_in_the_child_is_raised_here_with_its_message():
    def boom():
        raise ValueError("eval.reference: 'nonsense' is not a classical controller")

    with pytest.raises(RuntimeError, match=r"the reference failed in its child process: ValueError: eval.reference: "
                                           r"'nonsense' is not a classical controller"):
        Background(boom, name="the reference").result()


def test_a_child_that_dies_without_an_answer_is_named_with_its_exit_code():
    job = Background(lambda: os.kill(os.getpid(), signal.SIGKILL), name="the reference")
    with pytest.raises(RuntimeError, match=r"the reference: the child process ended without an answer \(exit code -9\)"):
        job.result()
