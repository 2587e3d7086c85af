// Node module-resolution hook: the bare specifier 'rp2040js' (imported by
// ../shared/emulator/rp2run.mjs and by host.mjs) resolves to the pinned copy
// that tests/chip/conftest.py installs in the project's cache folder
// (.cache/chip/node_modules), so ../shared/emulator is used in place, unmodified.
let parent = null;

export async function initialize(data) {
  parent = data.parentURL; // a file URL inside the cache folder
}

export async function resolve(specifier, context, nextResolve) {
  if (parent && (specifier === 'rp2040js' || specifier.startsWith('rp2040js/'))) {
    return nextResolve(specifier, { ...context, parentURL: parent });
  }
  return nextResolve(specifier, context);
}
