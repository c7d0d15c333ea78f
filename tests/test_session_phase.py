"""A session core's phase (:class:`dinerdash._session.Phase`) changes only as the module's doc
says: each transition by its method, from the phases it allows; any other raises
:class:`~dinerdash._session.IllegalTransition`, an internal error that names the call and the
phase. Two real sessions on the test server, moved by hand through a transfer, a drain and a
loss (the fleet's tests run the same methods under real failovers and drains)."""

from __future__ import annotations

import pytest
from dinerdash import ConnectOptions
from dinerdash._batch import Batch
from dinerdash._endpoint import Endpoint
from dinerdash._session import IllegalTransition, Phase, SessionCore, Settings
from gymnasium.vector import AutoresetMode


def test_a_core_changes_phase_only_as_documented(address: str) -> None:
    endpoint = Endpoint(ConnectOptions(address=address))
    settings = Settings(num_envs=4, autoreset_mode=AutoresetMode.NEXT_STEP)
    source = SessionCore(endpoint, 0, 0, 4, settings)
    new = SessionCore(endpoint, 0, 0, 4, settings)
    first = Batch(4, {})
    try:
        assert new.phase is Phase.NEW
        with pytest.raises(IllegalTransition, match=r"begin_receiving\(\) while new"):
            new.begin_receiving(source, first)
        source.create()
        new.create()
        assert source.phase is new.phase is Phase.SERVING
        for wrong in (new.finish_transfer, new.complete_transfer, lambda: new.enter([0])):
            with pytest.raises(IllegalTransition, match=r"while serving \(allowed only while"):
                wrong()
        new.begin_receiving(source, first)
        assert new.phase is Phase.RECEIVING and new.source is source and new.load == 0
        with pytest.raises(IllegalTransition, match=r"begin_receiving\(\) while receiving"):
            new.begin_receiving(source, first)
        new.await_entry([2, 1])
        assert new.take_entering() == [1, 2] and not new.entering
        new.enter([1, 2])
        assert new.holds(1) and new.holds(2) and not source.holds(1) and not new.holds(0)
        assert (new.load, source.load) == (2, 2)
        new.finish_transfer()
        assert new.phase is Phase.SERVING and new.source is None
        new.mark_draining()
        new.mark_draining()
        assert new.phase is Phase.DRAINING
        with pytest.raises(IllegalTransition, match=r"begin_receiving\(\) while draining"):
            new.begin_receiving(source, first)
        new.mark_lost()
        new.mark_draining()  # a lost core stays lost
        assert new.phase is Phase.LOST
        with pytest.raises(IllegalTransition, match=r"take_over\(\) while lost"):
            new.take_over(first, None, True)
        assert not new.take_reconnected()
    finally:
        source.close()
        new.close()
        endpoint.close()
    assert source.phase is new.phase is Phase.CLOSED
    new.mark_lost()  # a closed core stays closed
    assert new.phase is Phase.CLOSED
