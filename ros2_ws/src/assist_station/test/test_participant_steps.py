"""The WebSocket participant takes a study step's result only from a view of another step: a station whose view of
the same step changes meanwhile (the last landing's bag closing: stage 'closing' -> 'idle') gets each step once."""
from __future__ import annotations

import asyncio
import json

from aiohttp import web

from assist_station.participant import Participant, draw_profiles, step_key


def test_step_key_is_the_protocol_step_not_the_stage():
    survey = {'type': 'study', 'participant': 'S01', 'phase': 'survey', 'stage': 'closing', 'in_flight': False}
    assert step_key(dict(survey, stage='idle')) == step_key(survey)
    assert step_key(dict(survey, phase='done')) != step_key(survey)
    assert step_key(dict(survey, in_flight=True)) != step_key(survey) and step_key(None) is None


def test_a_view_of_the_same_step_does_not_make_the_participant_send_it_again():
    profile = draw_profiles(1, seed=0, practice=0)[0]
    received: list[str] = []

    async def station(request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        view = {'type': 'study', 'participant': profile.pid, 'phase': 'survey', 'order': [], 'in_flight': False,
                'stage': 'closing', 'questions': []}
        await ws.send_str(json.dumps({'type': 'hello', 'role': 'pilot'}))
        await ws.send_str(json.dumps(view))
        async for msg in ws:
            action = json.loads(msg.data).get('action')
            received.append(action)
            if action != 'survey':
                continue
            if received.count('survey') > 1:          # what the study does with a second survey
                await ws.send_str(json.dumps({'type': 'study_error', 'message': 'no concluding survey now (the '
                                                                               'study is at done)'}))
                continue
            await ws.send_str(json.dumps(dict(view, stage='idle')))     # the bag closed: same step
            await asyncio.sleep(0.3)                                    # the survey saved a moment later
            await ws.send_str(json.dumps(dict(view, phase='done', stage='idle', thanks='thanks')))
        return ws

    async def main() -> dict:
        app = web.Application()
        app.router.add_get('/ws', station)
        runner = web.AppRunner(app)
        await runner.setup()
        site = web.TCPSite(runner, '127.0.0.1', 0)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]
        try:
            return await asyncio.wait_for(Participant(f'http://127.0.0.1:{port}', profile, connect_timeout_s=10).run(),
                                          30)
        finally:
            await runner.cleanup()
    result = asyncio.run(main())
    assert received == ['survey'] and result['reconnects'] == 0
