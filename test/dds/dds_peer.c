/* A plain Cyclone DDS C program for the gateway's tests: its types come from idlc (the IDL that
 * `lcmx idl` writes for dds_test.lcm, and lcmx_envelope.idl), it knows nothing of lcmx.
 *
 *   dds_peer read-typed   TOPIC COUNT   prints each sample's fields, one line each
 *   dds_peer write-typed  TOPIC COUNT   waits for a reader, writes COUNT samples, waits for acks
 *   dds_peer read-opaque  TOPIC COUNT   prints each envelope (channel, type, size, sum)
 *   dds_peer write-other  TOPIC         a writer of another type (the envelope) on TOPIC; waits on stdin
 *
 * Prints "ready" once its reader/writer exists. The network comes from CYCLONEDDS_URI; the
 * domain from DDS_PEER_DOMAIN. Exits 0 when done, 1 on timeout (20 s) or error. */
#include <dds/dds.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "dds_test.h"
#include "lcmx_envelope.h"

static void die(const char* what, dds_return_t rc) {
  fprintf(stderr, "dds_peer: %s: %s\n", what, dds_strretcode(rc));
  exit(1);
}

static dds_entity_t check(dds_entity_t e, const char* what) {
  if (e < 0) die(what, e);
  return e;
}

static dds_qos_t* reliable_qos(void) {
  dds_qos_t* q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  dds_qset_history(q, DDS_HISTORY_KEEP_ALL, 0);
  return q;
}

/* Waits (on a waitset, 20 s deadline) for `status` on `e`. */
static void wait_status(dds_entity_t pp, dds_entity_t e, uint32_t status, const char* what) {
  dds_set_status_mask(e, status);
  dds_entity_t ws = check(dds_create_waitset(pp), "waitset");
  dds_waitset_attach(ws, e, e);
  dds_time_t deadline = dds_time() + DDS_SECS(20);
  for (;;) {
    uint32_t st = 0;
    dds_get_status_changes(e, &st);
    if (st & status) break;
    if (dds_time() > deadline) {
      fprintf(stderr, "dds_peer: timeout waiting for %s\n", what);
      exit(1);
    }
    dds_waitset_wait(ws, NULL, 0, DDS_MSECS(100));
  }
  dds_delete(ws);
}

static double sum_bytes(const uint8_t* p, uint32_t n) {
  double s = 0;
  for (uint32_t i = 0; i < n; ++i) s += p[i];
  return s;
}

static void print_typed(const lcmx_ddstest_sample_t* s) {
  printf("sample seq=%lld i8=%d i16=%d i32=%d f=%g d=%g flag=%d b=%u name=%s fixed3=%g,%g,%g grid12=%d "
         "origin=%g/%s corner1=%g/%s n=%d values=%u",
         (long long)s->seq, s->i8, s->i16, s->i32, s->f, s->d, s->flag ? 1 : 0, s->b, s->name, s->fixed3[0],
         s->fixed3[1], s->fixed3[2], s->grid[1][2], s->origin.x, s->origin.label, s->corners[1].x,
         s->corners[1].label, s->n, s->values._length);
  for (uint32_t i = 0; i < s->values._length; ++i) printf("%s%g", i ? "," : ":", s->values._buffer[i]);
  printf(" blob=%u:%g m=%d points=%u", s->blob._length, sum_bytes(s->blob._buffer, s->blob._length), s->m,
         s->points._length);
  for (uint32_t i = 0; i < s->points._length; ++i)
    printf("%s%g/%s", i ? "," : ":", s->points._buffer[i].x, s->points._buffer[i].label);
  printf(" tags=%u", s->tags._length);
  for (uint32_t i = 0; i < s->tags._length; ++i) printf("%s%s", i ? "," : ":", s->tags._buffer[i]);
  printf("\n");
  fflush(stdout);
}

int main(int argc, char** argv) {
  if (argc < 3) {
    fprintf(stderr, "usage: dds_peer read-typed|write-typed|read-opaque|write-other TOPIC [COUNT]\n");
    return 2;
  }
  const char* mode = argv[1];
  const char* topic_name = argv[2];
  const int count = argc > 3 ? atoi(argv[3]) : 1;
  const char* dom = getenv("DDS_PEER_DOMAIN");
  const dds_domainid_t domain = dom ? (dds_domainid_t)atoi(dom) : 0;
  dds_entity_t pp = check(dds_create_participant(domain, NULL, NULL), "participant");
  const int typed = strstr(mode, "typed") != NULL;
  const dds_topic_descriptor_t* desc = typed ? &lcmx_ddstest_sample_t_desc : &lcmx_dds_Envelope_desc;
  dds_entity_t topic = check(dds_create_topic(pp, desc, topic_name, NULL, NULL), "topic");
  dds_qos_t* q = reliable_qos();

  if (strncmp(mode, "read", 4) == 0) {
    dds_entity_t rd = check(dds_create_reader(pp, topic, q, NULL), "reader");
    dds_delete_qos(q);
    printf("ready\n");
    fflush(stdout);
    int got = 0;
    dds_time_t deadline = dds_time() + DDS_SECS(20);
    dds_entity_t ws = check(dds_create_waitset(pp), "waitset");
    dds_entity_t rc = check(dds_create_readcondition(rd, DDS_ANY_STATE), "readcondition");
    dds_waitset_attach(ws, rc, rd);
    while (got < count) {
      if (dds_time() > deadline) {
        fprintf(stderr, "dds_peer: timeout: %d of %d samples\n", got, count);
        return 1;
      }
      dds_waitset_wait(ws, NULL, 0, DDS_MSECS(200));
      void* samples[8] = {NULL};
      dds_sample_info_t infos[8];
      int n;
      while ((n = dds_take(rd, samples, infos, 8, 8)) > 0) {
        for (int i = 0; i < n; ++i) {
          if (!infos[i].valid_data) continue;
          ++got;
          if (typed) {
            print_typed((const lcmx_ddstest_sample_t*)samples[i]);
          } else {
            const lcmx_dds_Envelope* e = (const lcmx_dds_Envelope*)samples[i];
            printf("envelope channel=%s type=%s fingerprint=%lld size=%u sum=%.0f\n", e->channel, e->type_name,
                   (long long)e->fingerprint, e->payload._length, sum_bytes(e->payload._buffer, e->payload._length));
            fflush(stdout);
          }
        }
        dds_return_loan(rd, samples, n);
        samples[0] = NULL;
      }
    }
    dds_delete(pp);
    return 0;
  }

  dds_entity_t wr = check(dds_create_writer(pp, topic, q, NULL), "writer");
  dds_delete_qos(q);
  printf("ready\n");
  fflush(stdout);
  if (strcmp(mode, "write-other") == 0) {
    lcmx_dds_Envelope e;
    memset(&e, 0, sizeof e);
    e.channel = (char*)"other";
    e.type_name = (char*)"other";
    dds_write(wr, &e);
    char line[64];
    (void)!fgets(line, sizeof line, stdin); /* until the test closes stdin */
    dds_delete(pp);
    return 0;
  }
  wait_status(pp, wr, DDS_PUBLICATION_MATCHED_STATUS, "a matched reader");
  printf("matched\n");
  fflush(stdout);
  for (int k = 0; k < count; ++k) {
    lcmx_ddstest_sample_t s;
    memset(&s, 0, sizeof s);
    double values[3] = {0.5, 1.5, 2.5 + k};
    uint8_t blob[3] = {1, 2, (uint8_t)(3 + k)};
    lcmx_ddstest_point_t pts[2] = {{10.0, (char*)"p0"}, {11.0, (char*)"p1"}};
    char* tags[2] = {(char*)"alpha", (char*)"beta"};
    s.seq = 1000 + k;
    s.i8 = -8;
    s.i16 = -1600;
    s.i32 = 320000;
    s.f = 1.25f;
    s.d = -2.5;
    s.flag = true;
    s.b = 200;
    s.name = (char*)"from-dds";
    s.fixed3[0] = 1; s.fixed3[1] = 2; s.fixed3[2] = 3;
    s.grid[1][2] = 12;
    s.origin.x = 7.5;
    s.origin.label = (char*)"o";
    s.corners[0].label = (char*)"c0";
    s.corners[1].x = 9.0;
    s.corners[1].label = (char*)"c1";
    s.n = 99; /* the gateway sets LCM's size member from the sequence length (3) */
    s.values._length = s.values._maximum = 3;
    s.values._buffer = values;
    s.blob._length = s.blob._maximum = 3;
    s.blob._buffer = blob;
    s.m = 2;
    s.points._length = s.points._maximum = 2;
    s.points._buffer = pts;
    s.tags._length = s.tags._maximum = 2;
    s.tags._buffer = tags;
    dds_return_t rc = dds_write(wr, &s);
    if (rc < 0) die("write", rc);
  }
  dds_return_t rc = dds_wait_for_acks(wr, DDS_SECS(10));
  if (rc < 0) die("wait_for_acks", rc);
  printf("written %d\n", count);
  fflush(stdout);
  char line[64];
  (void)!fgets(line, sizeof line, stdin); /* stay until the test closes stdin */
  dds_delete(pp);
  return 0;
}
