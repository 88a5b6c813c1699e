#!/usr/bin/env node
// Independent MCAP validator built on the official TypeScript reader (@mcap/core), so that files written by
// drivebench's Python writer are checked by the code Foxglove/Lichtblick actually use to open them.
// Each file is read twice and the two readings are cross-checked:
//   1. indexed (McapIndexedReader): footer, summary CRC, chunk CRCs, message indexes, log-time order, Statistics;
//   2. stream (McapStreamReader): every record, trailing magic, data-section CRC; same messages as pass 1.
// Exit codes: 0 all files ok, 1 some file invalid, 2 some file truncated and none otherwise invalid.
import { createReadStream } from "node:fs";
import { open } from "node:fs/promises";
import { parseArgs } from "node:util";

const USAGE = "usage: node validate.mjs [--decode] [--require-viewable] [--json] FILE...";
const MAGIC = Buffer.from([0x89, 0x4d, 0x43, 0x41, 0x50, 0x30, 0x0d, 0x0a]); // "\x89MCAP0\r\n"
// Message encoding -> schema encodings Foxglove/Lichtblick display without extensions ("" = no schema).
const VIEWABLE = { protobuf: ["protobuf"], json: ["jsonschema", ""], flatbuffer: ["flatbuffer"], ros1: ["ros1msg"],
  cdr: ["ros2msg", "ros2idl", "omgidl"] };

let core, crc, support, nodejs; // loaded in main() so that a missing node_modules is one line, not a stack trace

const oneLine = (e) => String(e?.message ?? e).split("\n")[0];

// Per-channel count plus an order-independent fingerprint (sum of payload CRCs), so the two passes can be
// compared message-for-message without keeping the messages: an index that points at the wrong message
// (or at one message twice) changes the fingerprint even when the counts still agree.
function tally(perChannel, msg) {
  const entry = perChannel.get(msg.channelId) ?? { count: 0, fingerprint: 0 };
  entry.count += 1;
  entry.fingerprint = (entry.fingerprint + crc.crc32(msg.data)) >>> 0;
  perChannel.set(msg.channelId, entry);
}

// Pass 1: what a viewer sees. Initialize() checks magic, header, footer and summary CRC; readMessages()
// checks chunk CRCs and that each message-index entry points at a Message with the indexed log time.
// It never checks that the Message is on the channel its MessageIndex names, so we read topic by topic,
// as a viewer panel does, and check that every message returned belongs to the topic asked for.
async function indexedPass(path, handlers) {
  const out = { errors: [], perChannel: new Map(), messages: 0, reader: undefined, complete: false };
  const handle = await open(path, "r");
  try {
    const reader = await core.McapIndexedReader.Initialize({
      readable: new nodejs.FileHandleReadable(handle),
      decompressHandlers: handlers,
    });
    out.reader = reader;
    for (const topic of new Set([...reader.channelsById.values()].map((c) => c.topic))) {
      await readTopic(reader, topic, out);
    }
    out.complete = true;
  } catch (e) {
    out.errors.push(`indexed read: ${oneLine(e)}`);
  } finally {
    await handle.close();
  }
  return out;
}

async function readTopic(reader, topic, out) {
  let previous, disorders = 0, firstDisorder, strangers = 0;
  for await (const msg of reader.readMessages({ topics: [topic], validateCrcs: true })) {
    // The reader merges chunks through a heap; we check rather than trust that the result is ordered.
    if (previous !== undefined && msg.logTime < previous) {
      firstDisorder ??= `log time ${msg.logTime} after ${previous}`;
      disorders += 1;
    }
    previous = msg.logTime;
    if (reader.channelsById.get(msg.channelId)?.topic !== topic) strangers += 1;
    if (out.minTime === undefined || msg.logTime < out.minTime) out.minTime = msg.logTime;
    if (out.maxTime === undefined || msg.logTime > out.maxTime) out.maxTime = msg.logTime;
    out.messages += 1;
    tally(out.perChannel, msg);
  }
  const where = `topic "${topic}" (indexed read)`;
  if (disorders) out.errors.push(`${where}: ${disorders} messages out of log-time order, first ${firstDisorder}`);
  if (strangers) out.errors.push(`${where}: ${strangers} messages indexed under it belong to another topic`);
}

// A decoder per channel: a function that throws on bad bytes. A channel that cannot be decoded at all
// (e.g. a broken schema) gets a function that always throws, so every message counts as a failure.
function makeDecoder(channel, schema) {
  try {
    if (channel.messageEncoding === "json") {
      const text = new TextDecoder("utf-8", { fatal: true }); // invalid UTF-8 is as unviewable as bad JSON
      return (data) => JSON.parse(text.decode(data));
    }
    if (channel.messageEncoding === "protobuf") {
      if (schema?.encoding !== "protobuf") {
        throw new Error(`needs a "protobuf" schema, has ${schema ? `"${schema.encoding}"` : "none"}`);
      }
      const type = support.protobufFromBinaryDescriptor(schema.data).lookupType(schema.name);
      return (data) => type.decode(data);
    }
    return () => {}; // other encodings have no decoder here; --require-viewable judges them
  } catch (e) {
    return () => { throw e; };
  }
}

function decodeMessage(out, msg) {
  let state = out.decoders.get(msg.channelId);
  if (!state) {
    const channel = out.channels.get(msg.channelId);
    state = { decode: makeDecoder(channel, out.schemas.get(channel.schemaId)), failures: 0, first: "" };
    out.decoders.set(msg.channelId, state);
  }
  try {
    state.decode(msg.data);
  } catch (e) {
    if (state.failures++ === 0) state.first = `sequence ${msg.sequence} (log time ${msg.logTime}): ${oneLine(e)}`;
  }
}

// Pass 2: every record in file order, as a recovery tool would read it. The stream reader checks record
// framing, chunk CRCs, trailing magic and channel-before-message; we add the data-section CRC.
async function streamPass(path, opts, handlers) {
  const out = { errors: [], perChannel: new Map(), messages: 0, channels: new Map(), schemas: new Map() };
  out.decoders = new Map();
  const reader = new core.McapStreamReader({ decompressHandlers: handlers, validateCrcs: true });
  let appended = 0, dataEnd, tail = Buffer.alloc(0);
  try {
    for await (const piece of createReadStream(path, { highWaterMark: 1 << 20 })) {
      if (reader.done()) throw new Error("bytes after the footer and trailing magic");
      reader.append(piece);
      appended += piece.length;
      tail = Buffer.concat([tail, piece]).subarray(-MAGIC.length); // to tell truncation from a corrupt length
      for (;;) {
        const offset = appended - reader.bytesRemaining(); // where the next top-level record starts
        const record = reader.nextRecord();
        if (!record) break;
        if (record.type === "Schema") out.schemas.set(record.id, record);
        else if (record.type === "Channel") out.channels.set(record.id, record);
        else if (record.type === "DataEnd") dataEnd = { offset, crc: record.dataSectionCrc };
        else if (record.type === "Message") {
          out.messages += 1;
          tally(out.perChannel, record);
          if (opts.decode) decodeMessage(out, record);
        }
      }
    }
    if (dataEnd?.crc) await checkDataCrc(path, dataEnd, out.errors); // 0 means "not computed" per the spec
  } catch (e) {
    out.errors.push(`stream read: ${oneLine(e)}`);
  }
  out.complete = reader.done();
  out.parsedBytes = appended - reader.bytesRemaining();
  out.size = appended;
  out.tail = tail; // the whole file when it is shorter than the magic
  return out;
}

// @mcap/core reads DataEnd.data_section_crc but never verifies it: CRC of every byte before the DataEnd record.
async function checkDataCrc(path, dataEnd, errors) {
  let value = crc.crc32Init();
  for await (const piece of createReadStream(path, { start: 0, end: dataEnd.offset - 1 })) {
    value = crc.crc32Update(value, piece);
  }
  value = crc.crc32Final(value);
  if (value !== dataEnd.crc) errors.push(`data section CRC ${value} (DataEnd says ${dataEnd.crc})`);
}

// Per-topic content problems: dangling schema ids, decode failures, and (optionally) unviewable encodings.
function topicErrors(str, opts) {
  const errors = [];
  for (const [id, channel] of str.channels) {
    const topic = `topic "${channel.topic}"`;
    const schema = str.schemas.get(channel.schemaId);
    if (channel.schemaId !== 0 && !schema) errors.push(`${topic}: schema ${channel.schemaId} is never defined`);
    const state = str.decoders.get(id);
    if (state?.failures) {
      const what = `${state.failures} of ${str.perChannel.get(id).count} ${channel.messageEncoding} messages`;
      errors.push(`${topic}: ${what} fail to decode; first at ${state.first}`);
    }
    const problem = opts.requireViewable && unviewable(channel.messageEncoding, schema?.encoding ?? "");
    if (problem) errors.push(`${topic}: ${problem}`);
  }
  return errors;
}

function unviewable(messageEncoding, schemaEncoding) {
  const allowed = VIEWABLE[messageEncoding];
  if (!allowed) return `message encoding "${messageEncoding}" is not viewable in Foxglove/Lichtblick`;
  if (allowed.includes(schemaEncoding)) return undefined;
  const wanted = allowed.map((a) => `"${a}"`).join(" or ");
  return `"${messageEncoding}" messages need a schema encoding ${wanted}, not "${schemaEncoding}"`;
}

// The indexed pass must find exactly the messages the stream pass finds: none hidden from a viewer, none twice.
function crossCheck(idx, str) {
  const errors = [];
  const reader = idx.reader;
  if (idx.messages !== str.messages) {
    errors.push(`${idx.messages} messages reachable through the indexes, ${str.messages} in the data section`);
  }
  for (const id of new Set([...idx.perChannel.keys(), ...str.perChannel.keys()])) {
    const a = idx.perChannel.get(id), b = str.perChannel.get(id);
    if (a?.count !== b?.count || a?.fingerprint !== b?.fingerprint) {
      const counts = `${a?.count ?? 0} vs ${b?.count ?? 0} messages`;
      errors.push(`channel ${id}: indexed and stream reads differ (${counts} or their contents)`);
    }
  }
  for (const [id, channel] of str.channels) {
    if (!reader.channelsById.has(id)) errors.push(`channel ${id} (topic "${channel.topic}") missing from the summary`);
  }
  return [...errors, ...checkStatistics(reader, idx)];
}

// Statistics is what a viewer shows as message counts and the timeline's extent, so it must tell the truth.
function checkStatistics(reader, idx) {
  const stats = reader.statistics;
  if (!stats) return ["no Statistics record in the summary"];
  const errors = [];
  const expect = (what, claimed, actual) => {
    if (BigInt(claimed) !== BigInt(actual)) errors.push(`Statistics ${what} is ${claimed}, actual ${actual}`);
  };
  expect("messageCount", stats.messageCount, idx.messages);
  expect("channelCount", stats.channelCount, reader.channelsById.size);
  expect("schemaCount", stats.schemaCount, reader.schemasById.size);
  expect("chunkCount", stats.chunkCount, reader.chunkIndexes.length);
  for (const id of new Set([...stats.channelMessageCounts.keys(), ...idx.perChannel.keys()])) {
    const claimed = stats.channelMessageCounts.get(id) ?? 0n;
    expect(`message count of channel ${id}`, claimed, idx.perChannel.get(id)?.count ?? 0);
  }
  if (idx.messages > 0) {
    expect("messageStartTime", stats.messageStartTime, idx.minTime);
    expect("messageEndTime", stats.messageEndTime, idx.maxTime);
  }
  return errors;
}

// The stream ran out of bytes without an error. That is a truncated recording unless the file still ends in
// MCAP magic (then a corrupt record length sent the reader past the end) or is too short to be MCAP at all.
function whyIncomplete(str) {
  if (str.tail.equals(MAGIC)) {
    return `stream read: the record at byte ${str.parsedBytes} runs past the end of the file (${str.size} bytes)`;
  }
  if (str.size < MAGIC.length && !str.tail.equals(MAGIC.subarray(0, str.size))) {
    return `not an MCAP file: ${str.size} bytes and no MCAP magic`;
  }
  return undefined;
}

async function validateFile(path, opts, handlers) {
  const result = { file: path, ok: false, truncated: false, messages: 0, channels: 0, errors: [] };
  try {
    const idx = await indexedPass(path, handlers);
    const str = await streamPass(path, opts, handlers);
    result.messages = idx.reader ? idx.messages : str.messages;
    result.channels = idx.reader ? idx.reader.channelsById.size : str.channels.size;
    const contentErrors = topicErrors(str, opts);
    if (!str.complete && str.errors.length === 0) {
      const damage = whyIncomplete(str);
      if (damage) str.errors.push(damage);
      else {
        // A plain truncation: the indexed pass's complaint (no footer) is the same fact, so it is not repeated.
        result.truncated = true;
        const what = `truncated: complete records end at byte ${str.parsedBytes} of ${str.size}, no footer`;
        result.errors = [what, ...contentErrors];
        return result;
      }
    }
    result.errors = [...idx.errors, ...str.errors, ...contentErrors];
    if (idx.complete && str.complete) result.errors.push(...crossCheck(idx, str));
  } catch (e) {
    result.errors.push(oneLine(e)); // e.g. the file cannot be opened
  }
  result.ok = result.errors.length === 0;
  return result;
}

async function main(argv) {
  const flags = { decode: { type: "boolean" }, "require-viewable": { type: "boolean" }, json: { type: "boolean" } };
  const { values, positionals: files } = parseArgs({ args: argv, options: flags, allowPositionals: true });
  const opts = { decode: values.decode, requireViewable: values["require-viewable"], json: values.json };
  if (files.length === 0) throw new Error(USAGE);
  [core, crc, support, nodejs] = await Promise.all(
    ["@mcap/core", "@foxglove/crc", "@mcap/support", "@mcap/nodejs"].map((name) => import(name)),
  );
  const handlers = await support.loadDecompressHandlers();
  let invalid = false, truncated = false;
  for (const file of files) {
    const r = await validateFile(file, opts, handlers);
    if (opts.json) console.log(JSON.stringify(r));
    else if (r.ok) console.log(`OK ${file}: ${r.messages} messages, ${r.channels} channels`);
    else console.log(`ERROR ${file}: ${r.errors.join("; ")}`);
    // A truncated file whose only error is the truncation itself exits 2; anything more is invalid.
    if (r.truncated) truncated = true;
    if (r.errors.length > (r.truncated ? 1 : 0)) invalid = true;
  }
  return invalid ? 1 : truncated ? 2 : 0;
}

main(process.argv.slice(2)).then(
  (code) => { process.exitCode = code; },
  (e) => {
    console.error(`mcap-validate: ${oneLine(e)}`);
    process.exitCode = 1;
  },
);
