// User-study panel of the pilot station: participant ID -> consent -> practice -> block 1 -> SUS -> block 2 ->
// SUS [-> block 3 -> SUS] -> concluding survey -> thanks. The station decides the phase (its 'study' messages:
// block<k>, sus<k>); this panel only shows it and sends the participant's steps ({type: 'study', action, ...})
// through the station's socket.
'use strict';
(function () {
  const panel = document.getElementById('study');
  const stats = window.stationStats;
  let view = null, lastKey = null, feedback = null, error = null;

  function send(action, data) {
    error = null;
    if (!window.stationSend(Object.assign({ type: 'study', action: action }, data || {}))) {
      error = 'Not connected to the station: wait for the connection and try again.';
      render(true);
    }
  }
  function esc(text) {
    const d = document.createElement('div');
    d.textContent = text == null ? '' : String(text);
    return d.innerHTML;
  }
  function button(id, text) { return `<button id="${id}" type="button">${esc(text)}</button>`; }
  function radios(name, n, labels) {
    let h = '';
    for (let i = 1; i <= n; i += 1) {
      h += `<label><input type="radio" name="${name}" value="${i}"> ${esc(labels ? labels[i - 1] : i)}</label>`;
    }
    return h;
  }
  function checks(name, labels) {
    return labels.map((l, i) => `<label><input type="checkbox" name="${name}" value="${i + 1}"> ${esc(l)}</label>`).join('');
  }
  function checked(name) {
    const el = panel.querySelector(`input[name="${name}"]:checked`);
    return el ? parseInt(el.value, 10) : null;
  }
  const isBlock = (p) => /^block[0-9]+$/.test(p);
  const isSus = (p) => /^sus[0-9]+$/.test(p);
  const CONDITION_TEXT = {
    unassisted: 'You fly on your own in this block.',
    assisted: 'The assistant flies along in this block.',
    assisted_cues: 'The assistant flies along in this block and shows what it intends: the platform it believes ' +
      'is yours highlighted, a light that is green when descending is safe and red when you should hold, and ' +
      'an arrow for how it pushes the drone.',
  };
  function feedbackText(fb) {
    let t = fb.success ? 'Landed on the goal platform.' : fb.crash ? 'Crashed.' : 'Missed the goal platform.';
    if (fb.offset_m) {
      const [x, y] = fb.offset_m;
      t += ` The drone ended ${Math.abs(x).toFixed(2)} m ${x >= 0 ? 'beyond' : 'short of'} and ` +
           `${Math.abs(y).toFixed(2)} m ${y >= 0 ? 'left' : 'right'} of the goal centre`;
      if (typeof fb.error_m === 'number') t += ` (${fb.error_m.toFixed(2)} m away)`;
      t += '.';
    }
    return t;
  }

  function render(force) {
    if (!view) return;
    const key = JSON.stringify([view.participant, view.phase, view.trial, view.in_flight, view.error, error,
      feedback && feedback.n]);
    if (!force && key === lastKey) return;
    lastKey = key;
    panel.classList.remove('hidden');
    panel.classList.toggle('flying', !!view.in_flight);
    const err = (error || view.error) ? `<p class="err" id="study-error">${esc(error || view.error)}</p>` : '';
    let h = '';
    const p = view.phase;
    if (p === 'participant') {
      h = `<h2>${esc(view.study)}</h2><p>Enter your participant ID.</p>` +
          '<input id="study-id" maxlength="32" autocomplete="off"> ' + button('study-begin', 'Begin');
    } else if (p === 'consent') {
      h = `<h2>Welcome, ${esc(view.participant)}</h2><p>${esc(view.intro)}</p><p>${esc(view.consent)}</p>` +
          button('study-consent', 'I agree, continue');
    } else if (p === 'practice' || isBlock(p)) {
      const what = p === 'practice' ? 'Practice landing' : `Block ${view.block}: landing`;
      if (view.in_flight) {
        h = `${esc(what)} ${view.trial} of ${view.of} - land on the green platform`;
      } else {
        h = `<h2>${esc(what)} ${view.trial} of ${view.of}</h2>`;
        if (p === 'practice' && feedback) h += `<p class="fb" id="study-feedback">${esc(feedbackText(feedback))}</p>`;
        if (p !== 'practice' && view.trial === 1) {
          h += `<p id="study-condition">${esc(CONDITION_TEXT[view.condition] || CONDITION_TEXT.unassisted)} ` +
            'No results are shown during the block.</p>';
        }
        h += `<p>${esc(view.intro)}</p>` + button('study-start', 'Start landing');
        if (view.can_stop_practice && view.trial > 1) h += button('study-stop-practice', 'Finish practice');
      }
    } else if (isSus(p)) {
      h = `<h2>Questionnaire: block ${view.block}</h2><p>1 = strongly disagree, 5 = strongly agree</p>`;
      view.items.forEach((text, i) => { h += `<div class="q"><div>${i + 1}. ${esc(text)}</div>${radios('sus-' + i, 5)}</div>`; });
      h += button('study-submit', 'Submit');
    } else if (p === 'survey') {
      h = '<h2>Concluding survey</h2><p>Statements: 1 = strongly disagree, 5 = strongly agree</p>';
      for (const q of view.questions) {
        const inputs = q.kind === 'multi' ? checks('q-' + q.id, q.options)
          : radios('q-' + q.id, q.options ? q.options.length : 5, q.options);
        h += `<div class="q"><div>${q.id}. ${esc(q.text)}</div>${inputs}</div>`;
      }
      h += button('study-submit', 'Submit');
    } else if (p === 'done') {
      h = `<h2>Done</h2><p id="study-thanks">${esc(view.thanks)}</p>`;
    }
    panel.innerHTML = h + err;
    wire(p);
    if (view.in_flight) {
      const v = document.getElementById('view');
      if (v) v.focus();
    }
  }

  function wire(p) {
    const on = (id, fn) => { const el = document.getElementById(id); if (el) el.addEventListener('click', fn); };
    on('study-begin', () => send('begin', { participant: document.getElementById('study-id').value.trim() }));
    on('study-consent', () => send('consent'));
    on('study-start', () => { feedback = null; send('start'); });
    on('study-stop-practice', () => { feedback = null; send('stop_practice'); });
    on('study-submit', () => {
      if (isSus(p)) {
        const answers = view.items.map((_, i) => checked('sus-' + i));
        if (answers.includes(null)) { error = 'Please answer every statement.'; render(true); return; }
        send('sus', { answers: answers });
      } else {
        const answers = {};
        for (const q of view.questions) {
          if (q.kind === 'multi') {
            answers[q.id] = Array.from(panel.querySelectorAll(`input[name="q-${q.id}"]:checked`)).map((el) => parseInt(el.value, 10));
          } else {
            const a = checked('q-' + q.id);
            if (a === null) { error = `Please answer question ${q.id}.`; render(true); return; }
            answers[q.id] = a;
          }
        }
        send('survey', { answers: answers });
      }
    });
  }

  window.stationStudy = {
    onMessage(msg) {
      if (msg.type === 'study') { view = msg; if (msg.feedback) feedback = Object.assign({ n: msg.trial }, msg.feedback); render(false); }
      else if (msg.type === 'study_error') { error = msg.message; stats.studyErrors = (stats.studyErrors || 0) + 1; render(true); }
      else if (msg.type === 'study_feedback') { feedback = Object.assign({ n: Date.now() }, msg); render(true); }
    },
  };
  // a study message the socket delivered while this script was still loading: show it now
  if (stats && stats.study) window.stationStudy.onMessage(stats.study);
})();
